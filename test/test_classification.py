"""Completion for classification: class mappings, the PointNet classifier, the report section, the evaluate part."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gd_completion.errors import EvaluationError
from gd_completion.evaluation import classification as cls
from gd_completion.model import GGDConfig, GGDNet, save_checkpoint
from gd_completion.synth.meshio import HELDOUT_MESHES, sample_surface
from gd_completion.synth.vehicles import VEHICLE_KINDS, generate_vehicle

TINY = GGDConfig(num_input=128, num_output=256, num_control=32, tree_arity=(8, 4, 7), encoder_h0=(16, 32),
                 encoder_h1=(32,), code_hidden=(64,), code_dim=32, tree_hidden=(32,), local_widths=(16,),
                 gcn_width=16, gcn_blocks=1)
FAST = cls.ClassifierSettings(epochs=1, batch_size=8, n_points=128)


def test_every_generator_kind_and_mesh_has_a_class(shared_data: Path) -> None:
    assert set(cls.KIND_CLASSES) == set(VEHICLE_KINDS)
    assert set(cls.KIND_CLASSES.values()) == set(cls.CLASSES)   # procedural shapes reach every class
    assert set(HELDOUT_MESHES) <= set(cls.MESH_CLASSES)
    assert set(cls.MESH_CLASSES.values()) <= set(cls.CLASSES)
    manifest = json.loads((shared_data / "vehicle-meshes" / "manifest.json").read_text())
    assert {Path(m["file"]).stem for m in manifest["meshes"]} == set(cls.MESH_CLASSES)
    for mesh in manifest["meshes"]:   # the manifest's categories agree (car, suv, van, bus)
        assert cls.MESH_CLASSES[Path(mesh["file"]).stem] == mesh["category"]
    assert {cls.MESH_CLASSES[m] for m in HELDOUT_MESHES} == {"car", "suv", "bus"}


def test_mesh_names_follow_build_dataset_numbering(shared_data: Path) -> None:
    from gd_completion.synth.dataset import build_dataset

    folder = shared_data / "vehicle-meshes"
    held = cls.mesh_names(folder, heldout=True)
    train = cls.mesh_names(folder)
    assert sorted(held) == sorted(HELDOUT_MESHES) and not set(train) & set(HELDOUT_MESHES) and len(train) == 12
    extents = {Path(m["file"]).stem: np.array(m["extent_m"])
               for m in json.loads((folder / "manifest.json").read_text())["meshes"]}
    data = build_dataset(6, 9_000_123, meshes_dir=folder, mesh_fraction=1.0, only_meshes=HELDOUT_MESHES, n_input=64,
                         n_gt=64)
    for kind, size in zip(data["kind"], data["true_size"]):   # mesh:<i> is held[i]: sizes within the 0.9-1.1 scale
        ratio = size / extents[held[int(kind[5:])]]
        assert np.all((ratio > 0.88) & (ratio < 1.12)), (kind, ratio)
    labels = cls.sample_classes(data["kind"], held)
    assert [cls.CLASSES[i] for i in labels] == [cls.MESH_CLASSES[held[int(k[5:])]] for k in data["kind"]]


def test_sample_classes() -> None:
    got = cls.sample_classes(["sedan", "pickup_load", "semi_trailer", "mesh:1", "trailer"], ["a", "public_bus"])
    assert [cls.CLASSES[i] for i in got] == ["car", "pickup", "truck", "bus", "trailer"]
    with pytest.raises(KeyError):
        cls.sample_classes(["hovercraft"])


def test_training_and_heldout_seeds_are_kept_apart() -> None:
    from gd_completion.evaluation.synthetic import EVAL_SEED

    assert cls.TRAIN_SEED < EVAL_SEED
    with pytest.raises(ValueError, match="reserved for evaluation"):
        cls.training_shapes(2, seed=EVAL_SEED)
    with pytest.raises(ValueError, match="below EVAL_SEED"):
        cls.synthetic_set(2, seed=cls.TRAIN_SEED)


def test_pandaset_labels_map_to_classes(shared_data: Path) -> None:
    from gd_completion.evaluation.pandaset_eval import is_vehicle_class

    labels: set[str] = set()
    for index in (0, 40, 79):
        records = json.loads((shared_data / "pandaset-002" / "cuboids" / f"{index:02d}.json").read_text())
        labels |= {str(r["label"]) for r in records}
    vehicles = {label for label in labels if is_vehicle_class(label)} | {"Towed Object"}
    assert vehicles <= set(labels) | {"Towed Object"} and len(vehicles) >= 4
    for label in vehicles:   # every vehicle label of the sequence is in the experiment
        assert cls.pandaset_classes(label) and set(cls.pandaset_classes(label)) <= set(cls.CLASSES), label
    assert cls.pandaset_classes("Car") == ("car", "suv")
    assert cls.pandaset_classes("Pickup Truck") == ("pickup",)
    assert cls.pandaset_classes("Other Vehicle - Construction Vehicle") == ("construction",)
    for other in labels - vehicles:   # pedestrians, cones, bicycles, ...: left out
        assert cls.pandaset_classes(other) == ()


def _shapes(kind: str, count: int, seed: int) -> np.ndarray:
    """Complete shapes of a kind in the normalised frame (centred, length 1), 512 surface points each."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        mesh = generate_vehicle(rng, kind).centered()
        out.append(sample_surface(mesh, 512, rng) / mesh.extent[0])
    return np.array(out, np.float32)


def test_classifier_is_deterministic_and_separates_bus_from_car() -> None:
    bus, car = cls.class_index("bus"), cls.class_index("car")
    train = np.concatenate([_shapes("bus", 16, 1), _shapes("sedan", 16, 2)])
    labels = np.array([bus] * 16 + [car] * 16)
    settings = cls.ClassifierSettings(epochs=4, batch_size=8, n_points=256)
    net, log = cls.train_classifier(train, labels, settings=settings, seed=3)
    again, _ = cls.train_classifier(train, labels, settings=settings, seed=3)
    other, _ = cls.train_classifier(train, labels, settings=settings, seed=4)
    for (name, a), b in zip(net.state_dict().items(), again.state_dict().values()):
        assert torch.equal(a, b), name
    assert any(not torch.equal(a, c) for a, c in zip(net.state_dict().values(), other.state_dict().values()))
    assert log.n_shapes == 32 and log.counts == {"car": 16, "bus": 16} and not net.training
    test = np.concatenate([_shapes("bus", 10, 5), _shapes("sedan", 10, 6)])
    predicted = cls.classify(net, test, n_points=256)
    assert np.mean(predicted == np.array([bus] * 10 + [car] * 10)) >= 0.9
    np.testing.assert_array_equal(predicted, cls.classify(again, list(test), n_points=256))


def test_fixed_count() -> None:
    small, big = np.arange(9, dtype=np.float32).reshape(3, 3), np.arange(300, dtype=np.float32).reshape(100, 3)
    out = cls.fixed_count([small, big], 10, seed=1)
    assert out.shape == (2, 10, 3)
    np.testing.assert_array_equal(out[0], small[np.arange(10) % 3])
    assert len(np.unique(out[1][:, 0])) == 10 and set(out[1][:, 0]) <= set(big[:, 0])
    np.testing.assert_array_equal(out, cls.fixed_count([small, big], 10, seed=1))
    with pytest.raises(ValueError):
        cls.fixed_count([np.zeros((0, 3))], 10)


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def test_tiny_experiment_renders_its_values(shared_data: Path) -> None:
    torch.manual_seed(0)
    model = GGDNet(TINY).eval()
    result = cls.evaluate_classification(model, mesh_dir=shared_data / "vehicle-meshes",
                                         pandaset=shared_data / "pandaset-002", train_samples=24, synthetic_samples=6,
                                         mesh_samples=4, max_vehicles=3, max_per_vehicle=1, settings=FAST,
                                         classifiers=2)
    assert [s.name for s in result.sets] == ["synthetic shapes", "held-out meshes", "PandaSet 002"]
    synthetic, meshes, pandaset = result.sets
    assert (synthetic.n, meshes.n) == (6, 4) and 1 <= pandaset.n <= 3
    assert set(meshes.truth) <= {"car", "suv", "bus"} and set(pandaset.truth) <= set(cls.PANDASET_CLASSES)
    assert [log.seed for log in result.train] == [cls.TRAIN_SEED, cls.TRAIN_SEED + 1]
    assert all(log.n_shapes == 24 and sum(log.counts.values()) == 24 for log in result.train)
    assert len(result.validation) == 2 and all(0.0 <= v <= 1.0 for v in result.validation)
    for s in result.sets:
        assert set(s.predicted) == set(cls.INPUT_NAMES)
        for name in cls.INPUT_NAMES:
            assert s.predicted[name].shape == (2, s.n) and s.correct[name].shape == (2, s.n)
            per_classifier = s.correct[name].mean(1)
            np.testing.assert_allclose(s.accuracies(name), per_classifier)
            assert s.accuracy(name) == pytest.approx(per_classifier.mean())
    text = cls.classification_section(result)
    assert text.startswith("## Completion for classification")
    header = next(line for line in text.splitlines() if line.startswith("| input") and "n = 6" in line)
    assert _cells(header)[1:] == ["synthetic shapes (n = 6)", "held-out meshes (n = 4)",
                                  f"PandaSet 002 (n = {pandaset.n})"]
    table = text.split("Accuracy (mean over the classifiers, their range in brackets):")[1].split("\n\nOn the")[0]
    rows = {_cells(line)[0]: _cells(line)[1:] for line in table.splitlines()
            if line.startswith("| ") and not line.startswith("| input")}
    assert list(rows) == [cls.INPUT_TITLES[n] for n in cls.INPUT_NAMES]
    for name in cls.INPUT_NAMES:   # the mean over the two classifiers and their range
        assert rows[cls.INPUT_TITLES[name]] == [
            f"{s.accuracy(name):.3f} ({s.accuracies(name).min():.3f}-{s.accuracies(name).max():.3f})"
            for s in result.sets]
    gains = meshes.accuracies("ggd_merge") - meshes.accuracies("input")
    assert (f"On the held-out meshes (n = 4): GGD-Net published - raw input = {gains.mean():+.3f} "
            f"({gains.min():+.3f} to {gains.max():+.3f})") in text
    assert f"seeds {cls.TRAIN_SEED}, {cls.TRAIN_SEED + 1}" in text
    assert "accuracy on complete shapes drawn like the training ones" in text
    assert "multi-frame aggregate, 2048 points" in text
    assert "### Per-class accuracy: PandaSet 002" in text
    assert "Misclassified (GGD-Net published, all 2 classifiers)" in text


def test_section_without_sets() -> None:
    log = cls.ClassifierLog(2, {"car": 2}, 0, FAST, 0.1, 1.0, 0.5, "test")
    text = cls.classification_section(cls.ClassificationResult([log], [0.5], [], notes=["nothing to classify"]))
    assert "No set was classified" in text and "nothing to classify" in text
    assert "1 PointNet (" in text and ": 0.500." in text


def test_bad_experiment_settings_are_refused_before_any_data() -> None:
    model = GGDNet(TINY).eval()
    for kwargs, message in (({"classifiers": 0}, "must be >= 1"), ({"validation_samples": 0}, "must be >= 1"),
                            ({"seed": cls.VALIDATION_SEED}, "would be the validation shapes")):
        with pytest.raises(ValueError, match=message):
            cls.evaluate_classification(model, train_samples=4, synthetic_samples=0, mesh_samples=0, **kwargs)


def test_confusions_count_every_classifier_of_the_arrays() -> None:
    truth = ["car", "bus"]
    accepted = np.eye(len(cls.CLASSES), dtype=bool)[[cls.class_index(t) for t in truth]]
    predicted = {n: np.full((3, 2), cls.class_index("car")) for n in cls.INPUT_NAMES}   # three classifiers
    correct = {n: accepted[np.arange(2), p] for n, p in predicted.items()}
    log = cls.ClassifierLog(2, {"car": 2}, 7, FAST, 0.1, 1.0, 0.5, "test")
    result = cls.ClassificationResult([log], [0.5], [cls.SetResult("synthetic shapes", "test", "complete", truth,
                                                                   predicted, correct)])
    assert "Misclassified (GGD-Net published): bus -> car 3." in cls.classification_section(result)


def test_an_empty_set_shows_dashes() -> None:
    empty = {n: np.zeros((2, 0), np.int64) for n in cls.INPUT_NAMES}
    result = cls.ClassificationResult([cls.ClassifierLog(2, {"car": 2}, 7, FAST, 0.1, 1.0, 0.5, "test")] * 2,
                                      [0.5, 0.5], [cls.SetResult("held-out meshes", "test", "complete", [], empty,
                                                                 {n: np.zeros((2, 0), bool) for n in empty})])
    text = cls.classification_section(result)
    table = text.split("their range in brackets):")[1].split("\n\n", 2)[1]
    assert "nan" not in text and "No synthetic set was classified" in text
    assert [_cells(line)[1] for line in table.splitlines()[2:]] == ["-"] * len(cls.INPUT_NAMES)


def test_one_classifier_shows_plain_accuracies() -> None:
    truth = ["car", "car", "bus", "bus"]
    accepted = np.eye(len(cls.CLASSES), dtype=bool)[[cls.class_index(t) for t in truth]]
    predicted = {n: np.array([[cls.class_index("car")] * 4]) for n in cls.INPUT_NAMES}
    correct = {n: accepted[np.arange(4), p] for n, p in predicted.items()}
    log = cls.ClassifierLog(2, {"car": 2}, 7, FAST, 0.1, 1.0, 0.5, "test")
    result = cls.ClassificationResult([log], [0.75], [cls.SetResult("synthetic shapes", "test", "complete", truth,
                                                                    predicted, correct)])
    text = cls.classification_section(result)
    rows = {_cells(line)[0]: _cells(line)[1:] for line in text.split("Accuracy:")[1].split("\n\nOn the")[0].splitlines()
            if line.startswith("| ") and not line.startswith("| input")}
    assert rows == {cls.INPUT_TITLES[n]: ["0.500"] for n in cls.INPUT_NAMES}
    assert "published - raw input = +0.000 (network output" in text
    assert "Misclassified (GGD-Net published): bus -> car 2." in text


def test_evaluate_command_classification_part(tmp_path: Path, shared_data: Path, capsys) -> None:
    from gd_completion.tools import evaluate

    torch.manual_seed(0)
    model_path = save_checkpoint(tmp_path / "tiny.pt", GGDNet(TINY))
    parser = argparse.ArgumentParser()
    evaluate.register(parser.add_subparsers())
    common = ["evaluate", "--model", str(model_path), "--synthetic-samples", "2", "--heldout-mesh-samples", "2",
              "--no-pandaset", "--threads", "1", "--classification-train-samples", "8",
              "--classification-samples", "3"]
    args = parser.parse_args(common + ["--output", str(tmp_path / "with")])
    assert args.func(args) == 0
    text = (tmp_path / "with" / "report.md").read_text()
    assert "## Completion for classification" in text and "synthetic shapes (n = 3)" in text
    assert "held-out meshes (n = 2)" in text and "PandaSet 002 (n =" not in text
    assert "- classification: " in text
    assert f"{cls.CLASSIFIERS} PointNets (" in text and f"{cls.ClassifierSettings.epochs} epochs" in text
    skipped = "classification part is skipped"
    for extra, message in ((["--classifiers", "0"], "at least one"), (["--classifier-epochs", "0"], "at least one"),
                           (["--classifiers", "2", "--no-classification"], skipped),
                           (["--classifier-epochs", "2", "--synthetic-samples", "0"], skipped)):
        bad = parser.parse_args(common + ["--output", str(tmp_path / "bad"), *extra])
        with pytest.raises(EvaluationError, match=message):
            bad.func(bad)
        assert not (tmp_path / "bad").exists()
    args = parser.parse_args(common + ["--output", str(tmp_path / "two"), "--classifiers", "2",
                                       "--classifier-epochs", "1"])
    assert args.func(args) == 0
    text = (tmp_path / "two" / "report.md").read_text()
    assert "2 PointNets (" in text and "; 1 epochs," in text
    args = parser.parse_args(common + ["--output", str(tmp_path / "without"), "--no-classification"])
    assert args.func(args) == 0
    text = (tmp_path / "without" / "report.md").read_text()
    assert "Completion for classification" not in text and "classification:" not in text
    capsys.readouterr()


def test_evaluate_help_states_the_classification_defaults() -> None:
    """The command's help repeats the defaults as text (the module is imported only when the part runs): they are
    the module's own."""
    from gd_completion.tools import evaluate

    parser = argparse.ArgumentParser()
    evaluate.register(parser.add_subparsers())
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices["evaluate"]
    helps = {a.option_strings[0]: a.help for a in sub._actions if a.option_strings}
    assert f"(default {cls.CLASSIFIERS}:" in helps["--classifiers"]
    assert f"(default {cls.ClassifierSettings.epochs})" in helps["--classifier-epochs"]
