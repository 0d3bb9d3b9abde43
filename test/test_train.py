"""Training loop tests: loss decreases, determinism, resume from last.pt, time budget, bad data."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from test_model import TINY

from gd_completion.errors import CheckpointError, DataFormatError, TrainingError
from gd_completion.model import GGDConfig, GGDNet, load_model, read_checkpoint_metadata
from gd_completion.train import TrainSettings, train, warm_start

REPO = Path(__file__).resolve().parents[1]


def _data(n: int, seed: int):
    rng = np.random.default_rng(seed)
    complete = (rng.random((n, TINY.num_output, 3), dtype=np.float32) - 0.5) * np.array([1, 0.44, 0.4], np.float32)
    partial = complete[:, : TINY.num_input] * 1.0
    return partial, complete


def _settings(**kw):
    base = dict(epochs=2, generation_epochs=1, batch_size=4, lr=3e-3, seed=0)
    base.update(kw)
    return TrainSettings(**base)


def test_tiny_training_decreases_loss_and_writes_checkpoints(tmp_path):
    res = train(TINY, _data(8, 0), _data(4, 1), tmp_path, _settings(epochs=6, generation_epochs=6))
    hist = res.history
    assert len(hist) == 6 and res.epochs_done == 6 and not res.stopped_early
    assert [h["lam"] for h in hist] == [0.0] * 6
    assert hist[-1]["train_total"] < 0.7 * hist[0]["train_total"]
    assert (tmp_path / "last.pt").is_file() and (tmp_path / "best.pt").is_file()
    meta = read_checkpoint_metadata(tmp_path / "best.pt")
    assert meta["best_cd"] == pytest.approx(min(h["val_cd_completion"] for h in hist))
    assert load_model(tmp_path / "best.pt").config == TINY


def test_lambda_schedule_deterministic_and_resume(tmp_path):
    full = train(TINY, _data(8, 0), _data(4, 1), tmp_path / "full", _settings(epochs=3, generation_epochs=2))
    assert [h["lam"] for h in full.history] == [0.0, 0.0, 3.0]
    again = train(TINY, _data(8, 0), _data(4, 1), tmp_path / "again", _settings(epochs=3, generation_epochs=2))
    assert [h["train_total"] for h in again.history] == [h["train_total"] for h in full.history]
    # 2 epochs, then resume to 3: same result as 3 epochs in one go
    part = train(TINY, _data(8, 0), _data(4, 1), tmp_path / "part", _settings(epochs=2, generation_epochs=2))
    assert read_checkpoint_metadata(part.last_path)["epoch"] == 2
    res = train(TINY, _data(8, 0), _data(4, 1), tmp_path / "part", _settings(epochs=3, generation_epochs=2),
                resume=True)
    assert res.epochs_done == 3 and len(res.history) == 3
    assert res.history[-1]["train_total"] == pytest.approx(full.history[-1]["train_total"], rel=1e-5)
    a, b = load_model(res.last_path), load_model(full.last_path)
    for (k, va), (_, vb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert torch.allclose(va.float(), vb.float(), atol=1e-6), k


def test_time_budget_and_bad_data(tmp_path):
    res = train(TINY, _data(8, 0), _data(4, 1), tmp_path, _settings(epochs=50, time_budget_s=0.0))
    assert res.stopped_early and res.epochs_done == 0
    assert read_checkpoint_metadata(res.last_path)["epoch"] == 0
    bad = (np.zeros((4, 10, 3), np.float32), np.zeros((4, TINY.num_output, 3), np.float32))
    with pytest.raises(DataFormatError, match="training data"):
        train(TINY, bad, _data(4, 1), tmp_path / "bad", _settings())


def test_non_finite_training_data_is_a_clear_error(tmp_path):
    partial, complete = _data(8, 0)
    partial[2, 5, 1] = np.nan
    with pytest.raises(DataFormatError, match="training data partial: contains NaN or infinite"):
        train(TINY, (partial, complete), _data(4, 1), tmp_path, _settings(epochs=1))


def test_a_step_with_a_non_finite_loss_or_gradient_is_skipped_and_counted(tmp_path, monkeypatch, caplog):
    """One bad batch must not turn every weight into NaN; too many end the run with a clear error."""
    import gd_completion.train as training

    ggd_loss = training.ggd_loss
    calls = {"n": 0}

    def bad_every_other_step(output, *args, **kwargs):
        losses = ggd_loss(output, *args, **kwargs)
        calls["n"] += 1
        if calls["n"] % 4 == 1:     # a NaN loss
            losses["total"] = losses["total"] * float("nan")
        elif calls["n"] % 4 == 2:   # a finite loss (unchanged value) whose gradient is NaN
            losses["total"] = losses["total"] + torch.sqrt(output.completion.sum() * 0.0)
        return losses

    monkeypatch.setattr(training, "ggd_loss", bad_every_other_step)
    with caplog.at_level("WARNING", logger="gd_completion.train"):
        res = train(TINY, _data(8, 0), _data(4, 1), tmp_path, _settings(epochs=2, batch_size=2))
    assert [h["skipped_steps"] for h in res.history] == [2, 2]     # 4 steps an epoch, the first two bad
    assert "non-finite loss or gradient, step skipped" in caplog.text
    assert all(np.isfinite(h["train_total"]) for h in res.history)
    assert all(torch.isfinite(t).all() for t in load_model(res.last_path).state_dict().values())
    adam = torch.load(res.last_path, weights_only=True)["optimizer"]["state"][0]
    assert int(adam["step"]) == 4                                    # only the good steps were taken
    with pytest.raises(TrainingError, match="more than 1 steps"):
        train(TINY, _data(8, 0), _data(4, 1), tmp_path / "strict", _settings(batch_size=2, max_skipped_steps=1))


def test_an_epoch_without_one_finite_step_is_an_error(tmp_path, monkeypatch):
    import gd_completion.train as training

    ggd_loss = training.ggd_loss

    def always_nan(*args, **kwargs):
        losses = ggd_loss(*args, **kwargs)
        losses["total"] = losses["total"] * float("nan")
        return losses

    monkeypatch.setattr(training, "ggd_loss", always_nan)
    with pytest.raises(TrainingError, match="every step had a non-finite loss or gradient"):
        train(TINY, _data(8, 0), _data(4, 1), tmp_path, _settings(batch_size=4))


def test_warm_start_copies_matching_tensors_only(tmp_path):
    res = train(TINY, _data(8, 0), _data(4, 1), tmp_path / "src", _settings(epochs=1))
    source = load_model(res.last_path).state_dict()
    # another N_c: the last decoder level has another arity, so its tensors change shape
    other = GGDConfig(**{**TINY.to_dict(), "num_control": TINY.num_control * 2,
                         "tree_arity": (*TINY.tree_arity[:-1], (TINY.num_output - 2 * TINY.num_control)
                                        // int(np.prod(TINY.tree_arity[:-1])))})
    torch.manual_seed(1)
    model = GGDNet(other)
    fresh = warm_start(model, res.last_path, skip=("encoder.h1.0",))
    state = model.state_dict()
    assert fresh and all(k.startswith(("decoder.rest", "encoder.h1.0")) for k in fresh)
    assert any(k.startswith("encoder.h1.0") for k in fresh)
    for name, value in state.items():
        if name not in fresh:
            assert torch.equal(value, source[name]), name
        elif value.shape == source[name].shape:      # skipped by prefix: still its fresh initialisation
            assert not torch.equal(value, source[name]), name
    # and training from the warm start runs
    warm = train(other, (_data(8, 0)[0], _data(8, 0)[1]), _data(4, 1), tmp_path / "warm", _settings(epochs=1),
                 init_from=res.last_path)
    assert warm.epochs_done == 1
    from gd_completion.errors import CheckpointError
    with pytest.raises(CheckpointError, match="nope.pt: file not found"):
        train(other, _data(8, 0), _data(4, 1), tmp_path / "missing", _settings(epochs=1),
              init_from=tmp_path / "nope.pt")


# --- the train command's data cache ------------------------------------------------------------------------


def test_dataset_cache_is_keyed_on_what_shapes_the_data(tmp_path, monkeypatch, shared_data):
    from gd_completion.synth import cache as data_cache
    from gd_completion.synth.dataset import build_dataset, load_dataset, save_dataset

    meshes = tmp_path / "meshes"
    meshes.mkdir()
    (meshes / "taxi.ply").write_bytes((shared_data / "vehicle-meshes" / "basic_taxi.ply").read_bytes())
    builds = []

    def counting_build(*args, **kwargs):
        builds.append(kwargs)
        return build_dataset(*args, **kwargs)

    monkeypatch.setattr(data_cache, "build_dataset", counting_build)
    cache = tmp_path / "cache"
    spec = data_cache.DatasetSpec(2, 7, 32, 64, meshes)

    def cached():
        return data_cache.cached_dataset(cache, "train", spec, workers=1)

    first = cached()
    assert len(builds) == 1 and builds[0]["n_input"] == 32 and builds[0]["n_gt"] == 64
    assert first["partial"].shape == (2, 32, 3) and first["metadata"]["meshes_dir"] == str(meshes)
    [path] = cache.glob("*.npz")
    assert path.name.startswith("train_2_s7_")
    again = cached()
    assert len(builds) == 1 and again["metadata"]["cache_key"] == first["metadata"]["cache_key"]
    np.testing.assert_array_equal(again["partial"], load_dataset(path)["partial"])
    # another mesh in the folder (same folder, same count and seed): new data in a file of its own
    (meshes / "bus.ply").write_bytes((shared_data / "vehicle-meshes" / "public_bus.ply").read_bytes())
    cached()
    assert len(builds) == 2 and len(list(cache.glob("*.npz"))) == 2
    cached()
    assert len(builds) == 2
    # a new generator version, other sizes, another seed: each rebuilds
    monkeypatch.setattr(data_cache, "GENERATOR_VERSION", "gd_completion.synth/test")
    cached()
    spec = data_cache.DatasetSpec(2, 7, 16, 64, meshes)
    cached()
    spec = data_cache.DatasetSpec(2, 8, 16, 64, meshes)
    cached()
    assert len(builds) == 5 and len(list(cache.glob("*.npz"))) == 5
    # a file under the expected name without the key (an older cache) or corrupt is made again, not trusted
    [newest] = [p for p in cache.glob("train_2_s8_*.npz")]
    save_dataset(newest, build_dataset(2, 8, n_input=16, n_gt=64))
    cached()
    assert len(builds) == 6 and load_dataset(newest)["metadata"]["cache_key"]["seed"] == 8
    newest.write_bytes(b"not a zip")
    cached()
    assert len(builds) == 7 and load_dataset(newest)["metadata"]["meshes_dir"] == str(meshes)


def test_train_command_tiny_run(tmp_path, caplog):
    import logging

    from gd_completion.cli import main

    (tmp_path / "tiny.json").write_text(json.dumps(TINY.to_dict()))
    out = tmp_path / "run"
    argv = ["train", "--output", str(out), "--samples", "4", "--val-samples", "2", "--workers", "1", "--epochs", "1",
            "--generation-epochs", "1", "--batch-size", "2", "--config", str(tmp_path / "tiny.json")]
    assert main(argv) == 0
    settings = json.loads((out / "settings.json").read_text())
    assert settings["settings"]["device"] in ("cpu", "cuda")
    assert settings["data"]["n_input"] == TINY.num_input and settings["data"]["n_gt"] == TINY.num_output
    assert sorted(p.name.split("_")[0] for p in out.glob("*.npz")) == ["train", "val"]
    assert load_model(out / "last.pt").config == TINY
    caplog.clear()
    with caplog.at_level(logging.INFO):
        assert main(argv) == 0  # the second run reuses both data sets
    assert "loaded 4 cached samples" in caplog.text and "loaded 2 cached samples" in caplog.text
    assert "samples in" not in caplog.text  # "generated N samples in T s"


def test_box_conditioned_training_needs_sizes_and_learns_to_use_them(tmp_path):
    from dataclasses import replace

    from gd_completion.model.network import box_shape

    cfg = replace(TINY, box_conditioning=True)
    partial, complete = _data(8, 0)
    with pytest.raises(DataFormatError, match="box sizes"):
        train(cfg, (partial, complete), (partial[:2], complete[:2]), tmp_path / "a", _settings(epochs=1))
    sizes = np.tile(np.array([[4.5, 1.8, 1.5]], np.float32), (8, 1))
    sizes[::2, 1] = 2.4   # half of the boxes are wider
    bad = sizes.copy()
    bad[3, 2] = 0.0
    for wrong, what in ((sizes[:7], "shape \\(7, 3\\)"), (bad, "non-positive")):
        with pytest.raises(DataFormatError, match=what):
            train(cfg, (partial, complete, wrong), (partial[:2], complete[:2], sizes[:2]), tmp_path / "x",
                  _settings(epochs=1))
    res = train(cfg, (partial, complete, sizes), (partial[:2], complete[:2], sizes[:2]), tmp_path / "b",
                _settings(epochs=2))
    model = load_model(res.last_path)
    assert model.config.box_conditioning
    x = torch.from_numpy(partial[:1])
    with torch.inference_mode():
        narrow = model(x, box_shape([[4.5, 1.8, 1.5]])).completion
        wide = model(x, box_shape([[4.5, 2.4, 1.5]])).completion
        with pytest.raises(ValueError, match="box-conditioned"):
            model(x)
    assert not torch.equal(narrow, wide)   # the box shape reached the output


def test_train_command_from_a_recipe(tmp_path):
    from gd_completion.cli import main

    recipe = {"name": "tiny", "config": {**TINY.to_dict(), "box_conditioning": True}, "sampling": "v2",
              "samples": 4, "val_samples": 2, "epochs": 1, "generation_epochs": 1, "batch_size": 2, "seed": 3}
    path = tmp_path / "tiny_recipe.json"
    path.write_text(json.dumps(recipe))
    out = tmp_path / "run"
    assert main(["train", "--recipe", str(path), "--output", str(out), "--workers", "1"]) == 0
    settings = json.loads((out / "settings.json").read_text())
    assert settings["recipe"] == str(path) and settings["samples"] == 4 and settings["settings"]["seed"] == 3
    assert settings["data"]["options"]["box_noise_prob"] > 0   # the v2 sampling preset shaped the data
    assert load_model(out / "last.pt").config.box_conditioning
    # a shaping option both in the recipe and on the command line: refused, nothing trained
    assert main(["train", "--recipe", str(path), "--output", str(tmp_path / "b"), "--samples", "8"]) == 2
    assert not (tmp_path / "b" / "last.pt").exists()
    path.write_text(json.dumps({**recipe, "learning_rate": 0.1}))
    assert main(["train", "--recipe", str(path), "--output", str(tmp_path / "c")]) == 2
    path.write_text(json.dumps({**recipe, "sampling": "v9"}))
    assert main(["train", "--recipe", str(path), "--output", str(tmp_path / "d")]) == 2
    path.write_text("{not json")
    assert main(["train", "--recipe", str(path), "--output", str(tmp_path / "e")]) == 2
    path.write_text(json.dumps({**recipe, "sampling": {"box_noise_prob": 2.0}}))    # invalid options
    assert main(["train", "--recipe", str(path), "--output", str(tmp_path / "f")]) == 2
    path.write_text(json.dumps({**recipe, "config": {"no_such_field": 1}}))         # invalid configuration
    assert main(["train", "--recipe", str(path), "--output", str(tmp_path / "g")]) == 2
    assert not any((tmp_path / d).exists() for d in "cdefg")


def test_the_mesh_fraction_draws_that_share_of_the_shapes_from_the_meshes(tmp_path, shared_data):
    """`mesh_fraction` (recipe key, `--mesh-fraction`): 1 draws every training and validation shape from the meshes
    (keyed in the data's cache); outside [0, 1] or without meshes it is refused before any folder is made."""
    from gd_completion.cli import main
    from gd_completion.synth.dataset import load_dataset

    meshes = tmp_path / "meshes"
    meshes.mkdir()
    (meshes / "taxi.ply").write_bytes((shared_data / "vehicle-meshes" / "basic_taxi.ply").read_bytes())
    recipe = {"name": "tiny", "config": TINY.to_dict(), "samples": 6, "val_samples": 3, "epochs": 1,
              "generation_epochs": 1, "batch_size": 3, "seed": 5, "meshes": str(meshes), "mesh_fraction": 1.0}
    path = tmp_path / "recipe.json"
    path.write_text(json.dumps(recipe))
    out = tmp_path / "run"
    assert main(["train", "--recipe", str(path), "--output", str(out), "--workers", "1"]) == 0
    assert json.loads((out / "settings.json").read_text())["data"]["mesh_fraction"] == 1.0
    kinds = [str(k) for f in sorted(out.glob("*.npz")) for k in load_dataset(f)["kind"]]
    assert len(kinds) == 9 and all(k.startswith("mesh:") for k in kinds)
    # the default keeps some shapes procedural (the same seed: only the fraction differs)
    default = tmp_path / "default"
    path.write_text(json.dumps({k: v for k, v in recipe.items() if k != "mesh_fraction"}))
    assert main(["train", "--recipe", str(path), "--output", str(default), "--workers", "1"]) == 0
    kinds = [str(k) for f in sorted(default.glob("*.npz")) for k in load_dataset(f)["kind"]]
    assert len(kinds) == 9 and not all(k.startswith("mesh:") for k in kinds)
    for bad in ({**recipe, "mesh_fraction": 1.5}, {**recipe, "mesh_fraction": "all"}, {**recipe, "mesh_fraction": True},
                {k: v for k, v in recipe.items() if k != "meshes"}):
        path.write_text(json.dumps(bad))
        assert main(["train", "--recipe", str(path), "--output", str(tmp_path / "bad")]) == 2
    assert main(["train", "--output", str(tmp_path / "bad"), "--mesh-fraction", "0.5"]) == 2   # no meshes
    path.write_text(json.dumps(recipe))   # the flag and the recipe key both: one source of truth
    assert main(["train", "--recipe", str(path), "--output", str(tmp_path / "bad"), "--mesh-fraction", "0.5"]) == 2
    assert not (tmp_path / "bad").exists()


def test_cosine_learning_rate_schedule():
    s = TrainSettings(epochs=5, lr=1e-3, lr_final=1e-5)
    lrs = [s.lr_at(e) for e in range(5)]
    assert lrs[0] == pytest.approx(1e-3) and lrs[-1] == pytest.approx(1e-5)
    assert all(a > b for a, b in zip(lrs, lrs[1:]))
    assert lrs[2] == pytest.approx(0.5 * (1e-3 + 1e-5))
    assert TrainSettings(epochs=5, lr=2e-3).lr_at(4) == 2e-3   # constant by default


RECIPES = sorted(p for p in (REPO / "recipes").glob("*.json")   # ggd_v2_config is a model configuration;
                 if p.name != "ggd_v2_config.json" and not p.name.startswith("box_refiner"))   # refiner: its own


@pytest.mark.parametrize("path", RECIPES, ids=lambda p: p.stem)
def test_every_recipe_in_the_repository_is_valid(path, request, monkeypatch):
    """The recipes kept per training run parse with their sampling options and model configuration, as `train`
    reads them (no data generated), and warm-start from a run of the repository's recipes."""
    from gd_completion.cli import build_parser
    from gd_completion.tools.train import apply_recipe, drive_settings, load_config, sampling_options

    args = build_parser("train").parse_args(["train", "--output", "unused"])
    apply_recipe(args, path)
    sampling_options(args.sampling)
    if args.drive is not None:   # a labelled drive in ../shared, named relative to the repository like the CLI's
        request.getfixturevalue("shared_data")
        monkeypatch.chdir(REPO)
        drive_settings(args.drive)
    config = load_config(args)
    assert config.num_output == 2048 and args.samples > 0 and args.epochs > 0
    if args.init_from is not None:   # a run of another recipe, or weights kept in the repository
        start = Path(args.init_from)
        if start.parts[0] == "runs":
            assert (path.parent / f"{start.parent.name}.json").exists(), f"warm start from an unknown run: {start}"
        else:
            assert (REPO / start).is_file(), f"warm start from a missing file: {start}"


def test_the_repository_keeps_its_recipes():
    assert {p.stem for p in RECIPES} >= {"ggd_v2_stage1", "ggd_v2_stage4", "ggd_v2_stage5b", "ggd_v2_stage6"}


@pytest.mark.parametrize(("weights", "recipe_name", "epochs_done"), [
    ("docs/evaluation/ablation/ggd_v2_stage5b.pt", "ggd_v2_stage5b", None),   # v2's completion network
    ("docs/evaluation/ablation/ggd_v2_stage6.pt", "ggd_v2_stage6", None),     # measured, kept, not shipped
    ("docs/evaluation/ablation/ggd_v3_surface.pt", "ggd_v3_surface", 3),      # v3's first run: 3 of 5 epochs
    ("docs/evaluation/ablation/ggd_v3.pt", "ggd_v3b_noise", None),            # model v3
    ("docs/evaluation/ablation/ggd_v31.pt", "ggd_v3h_drive", None),           # model v3.1
    ("gd_completion/weights/ggd_vehicles.pt", "ggd_v3i_precision", None),     # shipped (model v3.2)
    ("docs/evaluation/ablation/ggd_v3k_meshes.pt", "ggd_v3k_meshes", None),   # measured, kept, not shipped
])
def test_kept_weights_come_from_the_recipe_that_claims_them(weights, recipe_name, epochs_done):
    """README, model card and MODEL.md name the recipe of each kept checkpoint: its schedule, seed, loss weights and
    configuration are the ones stored in the checkpoint (a run stopped early: its epochs done); where the recipe's
    notes quote the run's validation CD per epoch, the checkpoint's history holds those values (runs that differ only
    in their data, such as the mesh share, told apart)."""
    recipe = json.loads((REPO / "recipes" / f"{recipe_name}.json").read_text())
    meta = read_checkpoint_metadata(REPO / weights)
    assert meta["epoch"] == (epochs_done or recipe["epochs"]) == len(meta["history"])
    for key in ("epochs", "generation_epochs", "lam", "batch_size", "lr", "lr_final", "seed", "gamma", "freeze",
                "drive_weight", "drive_precision"):
        if key in recipe or (key in meta["settings"] and (not key.startswith("drive_") or "drive" in recipe)):
            expected = recipe.get(key, {"gamma": 0.0, "drive_weight": 1.0, "drive_precision": 0.0}.get(key, []))
            assert meta["settings"][key] == (tuple(expected) if key == "freeze" else expected), key
    assert GGDConfig.from_dict(meta["config"]) == GGDConfig.from_dict(recipe["config"])
    quoted = re.search(r"Validation:? CD\(P_o\) x1e3 ([0-9., ]+)", recipe.get("notes", ""))
    if quoted:
        values = [float(v) for v in quoted.group(1).strip(" ,.").split(",")]
        assert [h["val_cd_completion"] for h in meta["history"]] == pytest.approx(values, abs=1e-3)   # as rounded


def test_frozen_parameters_and_their_batch_norms_stay_as_they_are(tmp_path):
    """`freeze` keeps a refined network's box refiner exactly as it was (weights and running statistics) while
    the rest trains; a prefix that names nothing is an error."""
    from dataclasses import replace

    config = replace(TINY, box_conditioning=True, box_refinement=True, refiner_widths=(8, 16), refiner_hidden=(16,))
    start = tmp_path / "start.pt"
    torch.manual_seed(0)
    from gd_completion.model import save_checkpoint
    model = GGDNet(config)
    torch.nn.init.normal_(model.refiner.out.weight, std=0.1)   # a refiner that moves the frame
    save_checkpoint(start, model)
    partial, complete = _data(8, 0)
    sizes = np.tile(np.array([[4.5, 1.8, 1.5]], np.float32), (8, 1))
    res = train(config, (partial, complete, sizes), (partial[:4], complete[:4], sizes[:4]), tmp_path / "run",
                _settings(epochs=2, generation_epochs=0, freeze=("refiner.",)), init_from=start)
    before, after = model.state_dict(), load_model(res.last_path).state_dict()
    refiner = [k for k in before if k.startswith("refiner.")]
    assert any("running_mean" in k for k in refiner)
    assert all(torch.equal(before[k], after[k]) for k in refiner)
    assert not all(torch.equal(before[k], after[k]) for k in before if k.startswith("deform."))
    with pytest.raises(TrainingError, match="no parameter name starts with"):
        train(config, (partial, complete, sizes), (partial[:4], complete[:4], sizes[:4]), tmp_path / "bad",
              _settings(epochs=1, freeze=("refinr.",)), init_from=start)
    with pytest.raises(TrainingError, match="leaves no parameter to train"):
        train(config, (partial, complete, sizes), (partial[:4], complete[:4], sizes[:4]), tmp_path / "all",
              _settings(epochs=1, freeze=("",)), init_from=start)
    # a resume keeps the freeze of the run: another one is refused, the same one goes on
    with pytest.raises(CheckpointError, match="resume with the same freeze"):
        train(config, (partial, complete, sizes), (partial[:4], complete[:4], sizes[:4]), tmp_path / "run",
              _settings(epochs=3, generation_epochs=0), resume=True)
    resumed = train(config, (partial, complete, sizes), (partial[:4], complete[:4], sizes[:4]), tmp_path / "run",
                    _settings(epochs=3, generation_epochs=0, freeze=("refiner.",)), resume=True)
    assert len(resumed.history) == 3
    assert all(torch.equal(before[k], load_model(resumed.last_path).state_dict()[k]) for k in refiner)


def test_surface_term_is_the_unsquared_distance_and_trains_on_denser_targets(tmp_path):
    """The surface term is the mean Euclidean distance of each output point to its nearest target point (3-4-5:
    5 and 0 -> 2.5); with gamma > 0 it enters the loss after the generation epochs, and targets denser than N_o
    are accepted."""
    from gd_completion.model.losses import chamfer_and_surface, chamfer_l2, surface_distance

    points = torch.tensor([[[3.0, 4.0, 0.0], [0.0, 0.0, 1.0]]])
    gt = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [10.0, 0.0, 0.0]]])
    assert surface_distance(points, gt).tolist() == pytest.approx([2.5])
    clouds = torch.rand(2, 50, 3, generator=torch.Generator().manual_seed(1)), torch.rand(2, 80, 3)
    both = chamfer_and_surface(*clouds)   # one search serves the loss's two terms
    assert torch.equal(both[0], chamfer_l2(*clouds)) and torch.equal(both[1], surface_distance(*clouds))
    partial, complete = _data(16, 0)
    dense = np.concatenate([complete, complete[:, ::-1] * 0.999], axis=1)   # 2 N_o target points
    result = train(TINY, (partial, dense), (partial[:4], dense[:4]), tmp_path, _settings(gamma=1.0))
    first, second = result.history
    assert "train_surface" not in first and second["train_surface"] > 0   # lambda = 0, then lambda > 0
    assert second["val_surface"] > 0


def test_plane_distance_pulls_points_onto_the_surface_between_its_samples(tmp_path, capsys):
    """With the targets' normals the surface term is the distance to the nearest target point's tangent plane: a
    point 0.005 above a plane sampled 0.016 apart costs 0.005 (the point-to-point term: about twice that, most of it
    the distance along the surface to the nearest sample), its gradient points straight down the normal, and a point
    on the plane between samples costs nothing. Training with `surface_planes` uses it; the command line refuses it
    without a surface term to shape."""
    from gd_completion.cli import main
    from gd_completion.model.losses import ggd_loss, plane_distance, surface_distance, target_normals

    generator = torch.Generator().manual_seed(0)
    gt = torch.rand(2, 4096, 3, generator=generator) * torch.tensor([1.0, 1.0, 0.0])   # z = 0
    normals = target_normals(gt)
    assert normals.shape == gt.shape and torch.allclose(normals[..., 2].abs(), torch.ones(2, 4096))
    assert torch.equal(target_normals(gt, batch=1), normals)   # one sample at a time: the same
    points = torch.rand(2, 500, 3, generator=generator) * torch.tensor([0.8, 0.8, 0.0]) + torch.tensor([0.1, 0.1, 0.0])
    assert plane_distance(points, gt, normals).max() < 1e-5
    lifted = points + torch.tensor([0.0, 0.0, 0.005])
    lifted.requires_grad_(True)
    value = plane_distance(lifted, gt, normals)
    assert value.tolist() == pytest.approx([0.005, 0.005], rel=1e-4)
    assert (surface_distance(lifted, gt) > 1.5 * value).all()
    value.sum().backward()
    assert lifted.grad[..., :2].abs().max() < 1e-9 and (lifted.grad[..., 2] > 0).all()   # descent: down the normal
    # a tilted plane: the normals follow it (unoriented)
    tilted = gt.clone()
    tilted[..., 2] = 0.5 * gt[..., 0]
    expected = torch.tensor([-0.5, 0.0, 1.0]) / 1.25 ** 0.5
    assert torch.allclose((target_normals(tilted) @ expected).abs(), torch.ones(2, 4096), atol=1e-4)
    model = GGDNet(TINY).eval()
    partial, complete = _data(16, 0)
    out = model(torch.from_numpy(partial[:2]))
    target = torch.from_numpy(complete[:2])
    planar = ggd_loss(out, target, lam=3.0, gamma=2.0, normals=target_normals(target))
    assert planar["surface"].item() == pytest.approx(
        100 * plane_distance(out.completion, target, target_normals(target)).mean().item(), rel=1e-5)
    assert planar["surface"] < ggd_loss(out, target, lam=3.0, gamma=2.0)["surface"]
    dense = np.concatenate([complete, complete[:, ::-1] * 0.999], axis=1)   # more targets than N_o
    planes, points = (train(TINY, (partial, dense), (partial[:4], dense[:4]), tmp_path / name,
                            _settings(gamma=1.0, surface_planes=on)).history[1]
                      for name, on in (("planes", True), ("points", False)))
    # the same first epoch (lambda 0), then the training's surface term is the planes' distance, validation's not
    assert 0 < planes["train_surface"] < 0.8 * points["train_surface"]
    assert planes["val_surface"] == pytest.approx(points["val_surface"], rel=0.2)
    with pytest.raises(TrainingError, match="gamma > 0"):
        TrainSettings(surface_planes=True)
    assert main(["train", "--output", str(tmp_path / "cli"), "--surface-planes", "--samples", "4"]) == 2
    assert "gamma > 0" in capsys.readouterr().err and not (tmp_path / "cli").exists()


def test_train_overrides_are_checked_like_settings_and_leave_the_callers_settings_alone(tmp_path):
    """`train(**overrides)` builds checked settings: a bad weight or `surface_planes` without a surface term is
    refused before any folder is made, an unknown name is a TypeError, and a good override runs without changing the
    settings object the caller passed."""
    data = _data(4, 0)
    for bad, match in (({"surface_planes": True}, "gamma > 0"), ({"rho": -1.0}, "rho"),
                       ({"gamma": float("nan")}, "gamma")):
        with pytest.raises(TrainingError, match=match):
            train(TINY, data, data, tmp_path / "refused", _settings(), **bad)
    assert not (tmp_path / "refused").exists()
    with pytest.raises(TypeError, match="unknown setting 'mystery'"):
        train(TINY, data, data, tmp_path / "refused", _settings(), mystery=1)
    settings = _settings()
    result = train(TINY, data, data, tmp_path / "one", settings, epochs=1)
    assert result.epochs_done == 1 and settings.epochs == 2


def test_repulsion_term_pushes_clumped_points_apart_and_ignores_spread_ones(tmp_path):
    """The repulsion term is max(0, r - d)^2 averaged over every point's graph neighbours: 0 for points at least
    r apart, (r - d)^2 for a closer pair (both directions); its gradient moves the pair apart; with rho > 0 it
    enters the loss (rho 0: the loss as before, no such term)."""
    from gd_completion.model.losses import REPULSION_RADIUS, ggd_loss, repulsion

    r = REPULSION_RADIUS
    points = torch.tensor([[[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [1.0, 0.0, 0.0]]], requires_grad=True)
    knn = torch.tensor([[[1], [0], [1]]])   # the close pair, each way; the far point to the pair
    value = repulsion(points, knn)
    assert value.tolist() == pytest.approx([2 * (r - 0.01) ** 2 / 3])
    value.sum().backward()
    assert points.grad[0, 0, 0] > 0 > points.grad[0, 1, 0]   # descent moves them apart along x
    assert repulsion(points.detach() * 10, knn).tolist() == [0.0]   # spread out: no term
    partial, complete = _data(16, 0)
    result = train(TINY, (partial, complete), (partial[:4], complete[:4]), tmp_path, _settings(rho=10.0))
    first, second = result.history
    assert first["train_repulsion"] > 0 and second["train_repulsion"] > 0
    model = GGDNet(TINY).eval()
    out = model(torch.from_numpy(partial[:2]))
    plain = ggd_loss(out, torch.from_numpy(complete[:2]), lam=3.0)
    pushed = ggd_loss(out, torch.from_numpy(complete[:2]), lam=3.0, rho=10.0)
    assert "repulsion" not in plain
    assert pushed["total"].item() == pytest.approx(plain["total"].item() + 10.0 * pushed["repulsion"].item())


def test_tangential_repulsion_spreads_along_the_plane_and_not_off_it():
    """With `tangential`, distances are measured within each point's least-squares plane: two points stacked along
    the normal of a flat neighbourhood count as coincident (the full term), and the gradient has no component along
    that normal, so the term cannot thicken the shell; in 3D the same pair is pushed apart along the normal."""
    from gd_completion.model.losses import REPULSION_RADIUS, repulsion

    r = REPULSION_RADIUS
    grid = [[x, y, 0.0] for x in (-0.1, 0.0, 0.1) for y in (-0.1, 0.0, 0.1) if (x, y) != (0.0, 0.0)]
    points = torch.tensor([[[0.0, 0.0, 0.002], [0.0, 0.0, -0.002], *grid]], requires_grad=True)
    n = points.shape[1]
    rows = [[1] + list(range(2, n)), [0] + list(range(2, n))]   # the pair: the other one and the grid
    rows += [[j for j in range(n) if j != i] for i in range(2, n)]   # the grid points: every other point
    knn = torch.tensor([rows])
    flat = repulsion(points, knn, tangential=True)
    assert flat.item() == pytest.approx(2 * r ** 2 / (n * (n - 1)), rel=1e-3)   # the pair: d = 0 within the plane
    flat.sum().backward()
    assert points.grad[0, :2, 2].abs().max() < 1e-9   # nothing along the normal
    points.grad = None
    repulsion(points, knn).sum().backward()
    assert points.grad[0, 0, 2] < 0 < points.grad[0, 1, 2]   # in 3D: descent moves the pair apart along z


@pytest.mark.parametrize("weights", [{"rho": -1.0}, {"gamma": -0.5}, {"rho": float("nan")}])
def test_a_negative_loss_weight_is_refused_before_any_training(weights, tmp_path, capsys):
    """A negative (or NaN) weight of an optional loss term is a one-line error, not a term silently left out; the
    command line refuses it before it makes a folder or generates any data."""
    from gd_completion.cli import main

    with pytest.raises(TrainingError, match="must be >= 0"):
        TrainSettings(**weights)
    option, value = next(iter(weights.items()))
    assert main(["train", "--output", str(tmp_path / "run"), f"--{option}", str(value), "--samples", "4"]) == 2
    assert "must be >= 0" in capsys.readouterr().err and not (tmp_path / "run").exists()


def test_drive_loss_counts_only_the_references_coverage():
    """A real drive's aggregate is partial: output points where it has none cost nothing, its points left uncovered
    do."""
    from gd_completion.model.losses import chamfer_l2_directional, coverage, drive_loss, near_reference_distance

    torch.manual_seed(0)
    model = GGDNet(TINY).eval()
    partial = torch.from_numpy(_data(2, 0)[0])
    with torch.inference_mode():
        out = model(partial)
    reference = out.completion[:, :40]                       # the output holds it, and far more besides
    assert coverage(reference, out.completion).abs().max() < 1e-12
    assert (chamfer_l2_directional(out.completion, reference)[0] > 1e-4).all()   # the Chamfer term would pay
    moved = reference + torch.tensor([0.0, 0.0, 0.1])
    assert torch.allclose(coverage(moved, out.completion), chamfer_l2_directional(moved, out.completion)[0])
    terms = drive_loss(out, moved, lam=3.0)
    assert terms["coverage_fine"] > 0 and terms["total"] == pytest.approx(
        (terms["coverage_coarse"] + 3 * terms["coverage_fine"] + 1000 * terms["control"] + 0.5 * terms["shape"]).item())
    assert "near_reference" not in terms
    # the precision term: a point within the cap of the reference pays its distance, a farther one the cap, unpulled
    precise = drive_loss(out, moved, lam=3.0, precision=2.0, cap=0.05)
    distance = torch.cdist(out.completion, moved).min(-1).values
    assert 0 < (distance < 0.05).float().mean() < 1   # both kinds of points are there
    assert precise["near_reference"].item() == pytest.approx(100 * distance.clamp(max=0.05).mean().item(), rel=1e-4)
    assert precise["total"].item() == pytest.approx(terms["total"].item() + 2.0 * precise["near_reference"].item(),
                                                    rel=1e-5)
    points = out.completion.clone().requires_grad_(True)
    near_reference_distance(points, moved, cap=0.05).sum().backward()
    pulled = points.grad.norm(dim=-1) > 0
    assert torch.equal(pulled, distance < 0.05)


def test_training_with_a_drive_adds_its_batches_and_validates_on_it(tmp_path):
    """Drive pairs (partial, reference) join every step with their weight; the history gets their coverage, and the
    best checkpoint is chosen on the validation objective (P_o's CD + drive_weight x the drive's coverage)."""
    partial, complete = _data(8, 0)
    drive = ((partial[:6], complete[:6, : TINY.num_output // 2]), (partial[6:], complete[6:, : TINY.num_output // 2]))
    res = train(TINY, _data(8, 0), _data(4, 1), tmp_path / "d", _settings(epochs=4, generation_epochs=1,
                                                                      drive_weight=2.0), drive=drive)
    hist = res.history
    assert all("train_drive_coverage_fine" in h and "val_drive_coverage" in h for h in hist)
    assert [h["val_objective"] for h in hist] == pytest.approx(
        [h["val_cd_completion"] + 2.0 * h["val_drive_coverage"] for h in hist])
    assert read_checkpoint_metadata(tmp_path / "d" / "best.pt")["best_cd"] == pytest.approx(
        min(h["val_objective"] for h in hist))
    assert hist[-1]["val_drive_coverage"] < hist[0]["val_drive_coverage"]
    plain = train(TINY, _data(8, 0), _data(4, 1), tmp_path / "p", _settings(epochs=1, generation_epochs=1))
    assert "val_drive_coverage" not in plain.history[0]
    assert plain.history[0]["train_total"] != pytest.approx(hist[0]["train_total"])
    with pytest.raises(DataFormatError, match="drive training data"):
        train(TINY, _data(8, 0), _data(4, 1), tmp_path / "x", _settings(epochs=1),
              drive=((partial[:6, :5], complete[:6]), drive[1]))
    with pytest.raises(TrainingError, match="drive_weight"):
        TrainSettings(drive_weight=-1.0)
    # resumed without the drive, with another weight or other drive pairs (another drive setting, e.g. ground_band),
    # best.pt would compare two different objectives: refused
    other = (drive[0], (partial[6:], complete[6:, 1 : TINY.num_output // 2 + 1]))
    for settings, with_drive in ((_settings(epochs=5, generation_epochs=1, drive_weight=2.0), None),
                                 (_settings(epochs=5, generation_epochs=1, drive_weight=1.0), drive),
                                 (_settings(epochs=5, generation_epochs=1, drive_weight=2.0), other)):
        with pytest.raises(CheckpointError, match=r"resume with the same drive \(settings and pairs\)"):
            train(TINY, _data(8, 0), _data(4, 1), tmp_path / "d", settings, resume=True, drive=with_drive)
    resumed = train(TINY, _data(8, 0), _data(4, 1), tmp_path / "d",
                    _settings(epochs=5, generation_epochs=1, drive_weight=2.0), resume=True, drive=drive)
    assert resumed.epochs_done == 5 and "val_drive_coverage" in resumed.history[-1]
    assert read_checkpoint_metadata(tmp_path / "d" / "best.pt")["objective"].startswith("cd + 2 x drive coverage of ")
    # a checkpoint from before objectives named their drive pairs cannot say which pairs it validated on: refused
    last = torch.load(tmp_path / "d" / "last.pt", map_location="cpu", weights_only=False)
    torch.save({**last, "objective": "cd + 2 x drive coverage"}, tmp_path / "d" / "last.pt")
    with pytest.raises(CheckpointError, match="written before objectives named their drive pairs"):
        train(TINY, _data(8, 0), _data(4, 1), tmp_path / "d", _settings(epochs=6, generation_epochs=1,
                                                                        drive_weight=2.0), resume=True, drive=drive)
    with pytest.raises(TrainingError, match="drive_precision"):
        TrainSettings(drive_precision=-1.0)


@pytest.mark.integration
def test_train_command_takes_a_real_drive_from_its_recipe(tmp_path, shared_data, capsys):
    """A recipe's `drive` (drive_frames.DriveSettings' fields) adds the drive's completion pairs, held-out vehicles
    validating; a bad one is refused before any folder is made."""
    from gd_completion.cli import main

    folder = str(shared_data / "pandaset-002")
    recipe = {"name": "tiny_drive", "config": {**TINY.to_dict(), "box_conditioning": True}, "sampling": "v2",
              "samples": 4, "val_samples": 2, "epochs": 1, "generation_epochs": 0, "batch_size": 2,
              "drive": {"pandaset": folder, "draws": 0, "val_share": 0.2}, "drive_weight": 3.0, "drive_precision": 1.0}
    path = tmp_path / "recipe.json"
    path.write_text(json.dumps(recipe))
    out = tmp_path / "run"
    assert main(["train", "--recipe", str(path), "--output", str(out), "--workers", "1"]) == 0
    settings = json.loads((out / "settings.json").read_text())
    assert settings["drive"]["pandaset"] == folder and settings["settings"]["drive_weight"] == 3.0
    assert settings["settings"]["drive_precision"] == 1.0
    record = read_checkpoint_metadata(out / "last.pt")["history"][0]
    assert record["val_drive_coverage"] > 0 and record["train_drive_total"] > 0
    assert record["train_drive_near_reference"] > 0
    empty = tmp_path / "empty_drive"
    (empty / "lidar").mkdir(parents=True)   # a drive folder without a labelled frame: refused before any folder
    for bad, message in (({"draws": 0}, "needs pandaset"), ({"pandaset": folder, "sigma": 1}, "unknown drive keys"),
                         ({"pandaset": str(tmp_path)}, "lidar/"), ({"pandaset": str(empty)}, str(empty))):
        path.write_text(json.dumps({**recipe, "drive": bad}))
        assert main(["train", "--recipe", str(path), "--output", str(tmp_path / "bad")]) == 2
        assert message in capsys.readouterr().err and not (tmp_path / "bad").exists()
    for name, other in (("drive_weight", "drive_precision"), ("drive_precision", "drive_weight")):   # no drive
        path.write_text(json.dumps({key: value for key, value in recipe.items() if key not in ("drive", other)}))
        assert main(["train", "--recipe", str(path), "--output", str(tmp_path / "bad")]) == 2
        assert f"a {name.replace('_', ' ')} without a drive" in capsys.readouterr().err
        assert not (tmp_path / "bad").exists()
