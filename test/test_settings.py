"""The one settings table: validated values, the offline defaults, and the command-line flags generated from it."""
from __future__ import annotations

import argparse
import math

import pytest

from gd_completion.settings import SETTINGS, CompletionSettings, SettingsError, add_flags, flag_name, from_args


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="t")
    add_flags(p)
    return p


def test_node_and_offline_defaults_differ_only_where_the_table_says():
    node, offline = CompletionSettings.from_values({}), CompletionSettings.offline()
    assert node.limits.time_budget_s == 2.0 and offline.limits.time_budget_s == math.inf
    assert node.reuse is not None and node.reuse.budget_s == 0.03 and offline.reuse is None
    assert CompletionSettings.offline(reuse=True).reuse.budget_s == math.inf   # offline: never a frame budget
    assert (node.labels, node.class_preset, node.class_map, node.use_tf) == (("car", "van", "truck"), "names", (),
                                                                              True)
    assert from_args(parser().parse_args([])) == offline


def test_every_flag_reaches_its_setting():
    args = parser().parse_args(["--threads", "3", "--labels", "car,truck", "--class-preset", "openpcdet_kitti",
                                "--class-map", "7:car,SUV:car", "--no-use-tf", "--reuse", "--max-boxes", "9",
                                "--time-budget", "0.5", "--track-ids", "message", "--no-fusion-align",
                                "--no-input-points", "--model", "m.pt"])
    s = from_args(args)
    assert (s.num_threads, s.labels, s.class_preset, s.class_map, s.use_tf) == (
        3, ("car", "truck"), "openpcdet_kitti", ("7:car", "SUV:car"), False)
    assert s.classes["7"] == "car" and s.classes["1"] == "car" and s.classes["SUV"] == "car"
    assert s.reuse is not None and s.limits.max_boxes == 9 and s.limits.time_budget_s == 0.5
    assert (s.track_ids, s.fusion.align, s.include_input_points, s.model_path) == ("message", None, False, "m.pt")
    flags = {flag_name(name) for name in SETTINGS}
    assert {"--model", "--threads", "--no-input-points", "--reuse", "--no-measured-merge"} <= flags


@pytest.mark.parametrize("argv, message", [
    (["--max-boxes", "0"], "max_boxes=0 must be in [1, 100000]"),
    (["--threads", "two"], "invalid int 'two'"),
    (["--track-ids", "uuid"], "track_ids='uuid' must be one of ('associate', 'message', 'off')"),
    (["--class-preset", "yolo"], "class_preset='yolo' must be one of ('names'"),
])
def test_bad_flags_are_refused_with_the_reason(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        parser().parse_args(argv)
    assert exit_info.value.code == 2 and message in capsys.readouterr().err


@pytest.mark.parametrize("values, message", [
    ({"labels": ["bus"]}, "labels=['bus'] must be a non-empty subset"),
    ({"class_map": ["car"]}, "class_map: class_map entry 'car' is not of the form"),
    ({"crop_margin": -0.5}, "crop_margin=-0.5 must be -1"),
    ({"device": "gpu"}, "device='gpu' must be cpu, cuda or cuda:N"),
    ({"reuse_distance": "far"}, "reuse_distance='far' must be float"),
    ({"max_boxes": 10**9}, "max_boxes=1000000000 must be in"),
    ({"mystery": 1}, "unknown settings ['mystery']"),
])
def test_bad_values_name_the_setting(values, message):
    with pytest.raises(SettingsError) as info:
        CompletionSettings.from_values(values)
    assert message in str(info.value)
