"""Box refinement: frame maths against synthetic pairs whose box error is known, the refined GGDNet's contract,
and a refiner that learns a known offset (train_refiner, resumable, a whole checkpoint)."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import test_model
import torch

from gd_completion.errors import DataFormatError
from gd_completion.model.box_refiner import FRAME_UNITS, BoxFrame, frame_targets, from_frame, refined_shape, to_frame
from gd_completion.model.checkpoint import (
    DEFAULT_WEIGHTS,
    load_checkpoint,
    read_checkpoint_metadata,
    save_checkpoint,
)
from gd_completion.model.network import GGDNet, box_shape
from gd_completion.synth.dataset import SampleOptions, make_sample, sample_rng
from gd_completion.tools.train_refiner import SETTING_KEYS, read_recipe
from gd_completion.train_refiner import FrameData, RefinerSettings, mirrored_batch, train_refiner, with_refiner

TINY = replace(test_model.TINY, box_conditioning=True)


def _frame(b: int, seed: int = 0) -> BoxFrame:
    g = torch.Generator().manual_seed(seed)
    return BoxFrame.from_vector(torch.randn(b, 7, generator=g) * torch.tensor(FRAME_UNITS))


def _bbox_centre(points: np.ndarray) -> np.ndarray:
    return (points.min(0) + points.max(0)) / 2


def test_to_frame_and_from_frame_are_inverse():
    points = torch.rand(3, 50, 3) - 0.5
    frame = _frame(3)
    assert torch.allclose(from_frame(to_frame(points, frame), frame), points, atol=1e-6)
    assert not torch.allclose(to_frame(points, frame), points, atol=1e-3)
    assert torch.allclose(BoxFrame.from_vector(frame.to_vector()).scale, frame.scale)


def test_frame_targets_put_the_true_vehicle_at_the_origin():
    """Synthetic pairs cropped with a noisy box: their targets move the complete vehicle (normalised by the
    noisy box) to the centre of the frame and length 1; mirrored, the mirrored targets do the same."""
    opts = SampleOptions(box_noise_prob=1.0, box_center_sigma=0.3, box_yaw_sigma_deg=8.0, tilt_deg=0.0)
    before, after, mirrored_after = [], [], []
    for i in range(6):
        partial, complete, meta = make_sample(sample_rng(7, i), "sedan", n_input=64, n_gt=512, options=opts)
        target = frame_targets(meta["box_noise"][None], np.array([meta["yaw"]]), meta["size"][None],
                               meta["true_size"][None])
        gt = torch.from_numpy(complete)[None]
        placed = to_frame(gt, BoxFrame.from_vector(torch.from_numpy(target)))[0].numpy()
        before.append(np.abs(_bbox_centre(complete)[:2]).max())
        after.append(np.abs(_bbox_centre(placed)).max())
        assert np.ptp(placed[:, 0]) == pytest.approx(1.0, abs=0.03)    # the true length is 1
        flipped_gt, flipped_target = mirrored_batch(gt, torch.from_numpy(target), torch.tensor([True]))
        mirrored = to_frame(flipped_gt, BoxFrame.from_vector(flipped_target))[0].numpy()
        mirrored_after.append(np.abs(_bbox_centre(mirrored)).max())
        assert np.ptp(mirrored[:, 0]) == pytest.approx(1.0, abs=0.03)   # a wrong yaw sign tilts it: longer in x
        assert np.ptp(mirrored[:, 1]) == pytest.approx(np.ptp(placed[:, 1]), abs=1e-4)
        true_shape = refined_shape(box_shape(meta["size"][None]), BoxFrame.from_vector(torch.from_numpy(target)))
        assert torch.allclose(true_shape, box_shape(meta["true_size"][None]), atol=1e-5)
    assert max(after) < 0.02 and max(mirrored_after) < 0.02 and max(before) > 0.03, (before, after)


def test_an_identity_refiner_keeps_the_network_output():
    torch.manual_seed(0)
    base = GGDNet(TINY).eval()
    refined = with_refiner(base).eval()
    assert refined.config.box_refinement and refined.refiner is not None
    partial, shape = torch.rand(3, 64, 3) - 0.5, box_shape([[4.5, 1.8, 1.5]] * 3)
    with torch.inference_mode():
        a, b = base(partial, shape), refined(partial, shape)
    assert torch.equal(a.completion, b.completion) and torch.equal(a.coarse, b.coarse)


def test_a_refined_network_completes_in_the_refined_frame_and_maps_back():
    torch.manual_seed(0)
    base = GGDNet(TINY).eval()
    refined = with_refiner(base).eval()
    frame = _frame(1, seed=3)
    with torch.no_grad():   # a refiner that always answers `frame`
        refined.refiner.out.bias.copy_(frame.to_vector()[0] / refined.refiner.units)
    partial, shape = torch.rand(4, 64, 3) - 0.5, box_shape([[4.5, 1.8, 1.5], [5.0, 2.0, 1.6]] * 2)
    frames = BoxFrame(*(t.expand(4, *t.shape[1:]) for t in frame))
    with torch.inference_mode():
        got = refined(partial, shape)
        expected = base(to_frame(partial, frames), refined_shape(shape, frames))
        generated = refined.generate(partial, shape)
        one = refined(partial[2:3], shape[2:3])
    assert torch.allclose(got.completion, from_frame(expected.completion, frames), atol=1e-5)
    assert torch.allclose(generated, from_frame(expected.generated, frames), atol=1e-5)
    assert torch.allclose(got.control, partial.gather(1, got.control_index[..., None].expand(-1, -1, 3)), atol=1e-5)
    assert torch.equal(one.completion[0], got.completion[2])   # batch-independent in eval mode


def test_box_refinement_needs_box_conditioning():
    with pytest.raises(ValueError, match="box_conditioning"):
        replace(TINY, box_conditioning=False, box_refinement=True)


@pytest.mark.parametrize("widths, hidden", [((), (16,)), ((8, 0), (16,)), ((8,), (-4,))])
def test_refiner_sizes_are_checked(widths, hidden):
    with pytest.raises(ValueError, match="refiner"):
        replace(TINY, box_refinement=True, refiner_widths=widths, refiner_hidden=hidden)


def _offset_data(n: int, seed: int) -> FrameData:
    """Box-shaped clouds moved by a known centre offset (x, y) in the box frame, exact otherwise."""
    g = torch.Generator().manual_seed(seed)
    cloud = (torch.rand(n, 64, 3, generator=g) - 0.5) * torch.tensor([1.0, 0.4, 0.33])
    offset = (torch.rand(n, 2, generator=g) - 0.5) * 0.16
    target = torch.zeros(n, 7)
    target[:, :2] = offset
    cloud[..., :2] += offset[:, None]
    return FrameData(cloud, box_shape([[4.5, 1.8, 1.5]] * n), target)


def test_train_refiner_learns_a_known_offset_and_resumes(tmp_path):
    torch.manual_seed(0)
    base = tmp_path / "base.pt"
    save_checkpoint(base, GGDNet(TINY))
    train, val = _offset_data(512, 0), _offset_data(128, 1)
    settings = RefinerSettings(epochs=12, batch_size=32, lr=3e-3)
    first = train_refiner(base, train, val, tmp_path / "run", replace(settings, epochs=6))
    resumed = train_refiner(base, train, val, tmp_path / "run", settings, resume=True)
    assert len(first.history) == 6 and len(resumed.history) == 12 and resumed.history[:6] == first.history
    last = resumed.history[-1]
    assert last["val_rms_x"] < 0.5 * last["val_given_rms_x"] and last["val_rms_y"] < 0.5 * last["val_given_rms_y"]
    model, _ = load_checkpoint(first.best_path)
    assert model.config.box_refinement and model.refiner is not None
    assert model.refiner.out.weight.abs().sum() > 0   # trained away from the identity


def test_the_refiner_size_is_a_setting_kept_in_the_checkpoint(tmp_path):
    base = tmp_path / "base.pt"
    save_checkpoint(base, GGDNet(TINY))
    settings = RefinerSettings(epochs=1, batch_size=32, widths=[8, 16], hidden=[12])
    result = train_refiner(base, _offset_data(64, 0), _offset_data(32, 1), tmp_path / "run", settings)
    model, _ = load_checkpoint(result.best_path)
    assert (model.config.refiner_widths, model.config.refiner_hidden) == ((8, 16), (12,))
    assert [m.out_channels for m in model.refiner.points if isinstance(m, torch.nn.Conv1d)] == [8, 16]
    assert [m.out_features for m in model.refiner.head if isinstance(m, torch.nn.Linear)] == [12]


def test_a_refiner_step_with_a_non_finite_loss_or_gradient_is_skipped_and_counted(tmp_path, monkeypatch):
    import gd_completion.train_refiner as refiner_training
    from gd_completion.errors import TrainingError

    frame_loss = refiner_training.frame_loss
    calls = {"n": 0}

    def bad_steps(model, partial, shape, target):
        loss = frame_loss(model, partial, shape, target)
        calls["n"] += 1
        if calls["n"] % 4 == 1:     # a NaN loss
            return loss * float("nan")
        if calls["n"] % 4 == 2:     # a finite loss whose gradient is NaN
            return loss + torch.sqrt(model.refiner.vector(partial, shape).sum() * 0.0)
        return loss

    base = tmp_path / "base.pt"
    save_checkpoint(base, GGDNet(TINY))
    monkeypatch.setattr(refiner_training, "frame_loss", bad_steps)
    settings = RefinerSettings(epochs=2, batch_size=32)
    result = train_refiner(base, _offset_data(128, 0), _offset_data(32, 1), tmp_path / "run", settings)
    assert [h["skipped_steps"] for h in result.history] == [2, 2]   # 4 steps an epoch, the first two bad
    assert all(np.isfinite(h["train_loss"]) for h in result.history)
    model, _ = load_checkpoint(result.last_path)
    assert all(torch.isfinite(t).all() for t in model.state_dict().values())
    with pytest.raises(TrainingError, match="more than 1 steps"):
        train_refiner(base, _offset_data(128, 0), _offset_data(32, 1), tmp_path / "strict",
                      replace(settings, max_skipped_steps=1))
    monkeypatch.setattr(refiner_training, "frame_loss", lambda *args: frame_loss(*args) * float("nan"))
    with pytest.raises(TrainingError, match="every step had a non-finite loss"):
        train_refiner(base, _offset_data(64, 0), _offset_data(32, 1), tmp_path / "none", settings)


def _norm_statistics(path) -> torch.Tensor:
    model, _ = load_checkpoint(path)
    return torch.cat([m.running_mean for m in model.refiner.modules() if isinstance(m, torch.nn.BatchNorm1d)])


@pytest.mark.parametrize("norm_train_epochs, frozen", [(None, False), (1, True)])
def test_refiner_batch_norms_train_in_the_epochs_asked(tmp_path, norm_train_epochs, frozen):
    """Batch norms use batch statistics in every epoch, or only in the first `norm_train_epochs` (then their
    running statistics stay as they are), also across a resume."""
    torch.manual_seed(0)
    base = tmp_path / "base.pt"
    save_checkpoint(base, GGDNet(TINY))
    train, val = _offset_data(256, 0), _offset_data(64, 1)
    settings = RefinerSettings(epochs=2, batch_size=32, lr=3e-3, norm_train_epochs=norm_train_epochs)
    first = train_refiner(base, train, val, tmp_path / "run", replace(settings, epochs=1))
    after_one = _norm_statistics(first.last_path)
    second = train_refiner(base, train, val, tmp_path / "run", settings, resume=True)
    assert torch.equal(_norm_statistics(second.last_path), after_one) == frozen
    assert not torch.equal(after_one, torch.zeros_like(after_one))   # epoch 1 always updates them


def test_a_base_without_box_conditioning_is_refused(tmp_path):
    from gd_completion.errors import CheckpointError

    base = tmp_path / "plain.pt"
    save_checkpoint(base, GGDNet(replace(TINY, box_conditioning=False)))
    with pytest.raises(CheckpointError, match="box-conditioned"):
        train_refiner(base, _offset_data(64, 0), _offset_data(32, 1), tmp_path / "run", RefinerSettings(epochs=1))


def test_the_refined_frame_is_bounded():
    torch.manual_seed(0)
    refined = with_refiner(GGDNet(TINY)).eval()
    with torch.no_grad():
        refined.refiner.out.bias.fill_(1000.0)
        vector = refined.refiner.vector(torch.rand(1, 64, 3), box_shape([[4.5, 1.8, 1.5]]))
    assert torch.allclose(vector[0], refined.refiner.limits)


def test_frame_data_needs_the_box_error():
    with pytest.raises(DataFormatError, match="box_noise"):
        FrameData.from_datasets([{"partial": np.zeros((1, 4, 3)), "size": np.ones((1, 3))}])


def test_frame_data_refuses_non_finite_values():
    good = {"partial": np.zeros((2, 4, 3)), "box_noise": np.tile([0, 0, 0, 1, 1, 1, 0.0], (2, 1)),
            "yaw": np.zeros(2), "size": np.ones((2, 3)), "true_size": np.ones((2, 3))}
    assert len(FrameData.from_datasets([good])) == 2
    for key, row in (("partial", (0, 1, 2)), ("box_noise", (1, 6)), ("size", (0, 1))):
        bad = {k: np.array(v, np.float64) for k, v in good.items()}
        bad[key][row] = np.nan
        with pytest.raises(DataFormatError, match="non-finite|NaN"):
            FrameData.from_datasets([bad])


def test_refiner_recipe_is_checked(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"base": "x.pt", "data": [], "epoch": 3}))
    with pytest.raises(DataFormatError, match="epoch"):
        read_recipe(bad)


@pytest.mark.parametrize("sizes", [{"widths": 32}, {"widths": [32, 0]}, {"hidden": ["a"]}])
def test_refiner_recipe_sizes_are_checked_before_any_data(tmp_path, sizes):
    from gd_completion.tools.train_refiner import recipe_settings
    with pytest.raises(DataFormatError, match="recipe.json"):
        recipe_settings({"base": "x.pt", "data": ["y.json"], **sizes}, tmp_path / "recipe.json")


def test_a_base_refiner_of_other_sizes_is_refused_and_an_older_run_resumes(tmp_path):
    """A base that has a refiner keeps it only when the sizes asked are its own; a `last.pt` whose config lacks
    the refiner-size keys (written before they existed) resumes."""
    from gd_completion.errors import CheckpointError
    base = tmp_path / "base.pt"
    save_checkpoint(base, with_refiner(GGDNet(TINY), (8, 16), (12,)))
    with pytest.raises(CheckpointError, match="widths"):
        train_refiner(base, _offset_data(64, 0), _offset_data(32, 1), tmp_path / "other", RefinerSettings(epochs=1))
    plain = tmp_path / "plain.pt"   # a run of the default sizes, its last.pt as written before they were keys
    save_checkpoint(plain, GGDNet(TINY))
    settings = RefinerSettings(epochs=2, batch_size=32)
    first = train_refiner(plain, _offset_data(64, 0), _offset_data(32, 1), tmp_path / "run",
                          replace(settings, epochs=1))
    data = torch.load(first.last_path, weights_only=False)
    data["config"] = {k: v for k, v in data["config"].items() if k not in ("refiner_widths", "refiner_hidden")}
    torch.save(data, first.last_path)
    resumed = train_refiner(plain, _offset_data(64, 0), _offset_data(32, 1), tmp_path / "run", settings, resume=True)
    assert len(resumed.history) == 2


REPO = Path(__file__).resolve().parents[1]
# each refiner checkpoint in the repository and the recipe whose run it is
V22_WEIGHTS = REPO / "docs/evaluation/ablation/ggd_v22.pt"   # v2.2: the small refiner's run (model v3 builds on it)
REFINER_RUNS = [(V22_WEIGHTS, "box_refiner_small.json"),
                (REPO / "docs/evaluation/ablation/ggd_v21_refiner_large.pt", "box_refiner.json")]


@pytest.mark.parametrize("recipe_name", sorted(p.name for p in (REPO / "recipes").glob("box_refiner*.json")))
def test_the_repository_refiner_recipes_name_what_exists(recipe_name, request, monkeypatch):
    if "drive" in json.loads((REPO / "recipes" / recipe_name).read_text()):
        request.getfixturevalue("shared_data")   # a labelled drive of the shared data, beside the repository
    monkeypatch.chdir(REPO)                       # recipes name their files from the repository's root
    recipe = read_recipe(REPO / "recipes" / recipe_name)
    assert (REPO / recipe["base"]).is_file()
    assert all((REPO / r).is_file() for r in recipe["data"])


@pytest.mark.parametrize("weights, recipe_name", REFINER_RUNS)
def test_refiner_weights_are_their_recipe_on_its_frozen_base(weights, recipe_name):
    """The shipped checkpoint (and the kept larger refiner) is its recipe's run: its settings and sizes, and its
    base's weights unchanged (the refiner is the only part it trained)."""
    recipe = read_recipe(REPO / "recipes" / recipe_name)
    meta = read_checkpoint_metadata(weights)
    assert meta["base"] == recipe["base"] and meta["epoch"] == len(meta["history"]) == recipe["epochs"]
    settings = RefinerSettings(**{k: recipe[k] for k in SETTING_KEYS if k in recipe})
    saved = RefinerSettings(**{k: v for k, v in meta["settings"].items() if k in SETTING_KEYS})
    # the larger refiner's run predates the settings norm_train_epochs, widths and hidden (its config has its sizes)
    for key in SETTING_KEYS:
        if key in meta["settings"]:
            assert getattr(saved, key) == getattr(settings, key), key
    model, _ = load_checkpoint(weights)
    base, _ = load_checkpoint(REPO / recipe["base"])
    assert model.config == replace(base.config, box_refinement=True, refiner_widths=settings.widths,
                                   refiner_hidden=settings.hidden)
    state = model.state_dict()
    assert all(torch.equal(state[k], v) for k, v in base.state_dict().items())


def test_the_shipped_weights_keep_the_v22_refiner_frozen():
    """Model v3 fine-tuned v2.2's completion network with its box refiner frozen: every refiner tensor (weights and
    batch-norm statistics) is v2.2's, and the completion network did change."""
    shipped, v22 = load_checkpoint(DEFAULT_WEIGHTS)[0].state_dict(), load_checkpoint(V22_WEIGHTS)[0].state_dict()
    assert shipped.keys() == v22.keys()
    refiner = [k for k in v22 if k.startswith("refiner.")]
    assert refiner and all(torch.equal(shipped[k], v22[k]) for k in refiner)
    assert not all(torch.equal(shipped[k], v22[k]) for k in v22 if not k.startswith("refiner."))


def test_inference_folds_the_refiner_batch_norms_into_its_point_layers():
    """Under inference mode in eval the refiner's BN is folded into each Conv1d: the same vector as the modules
    give, for a batch and for one cloud, with the current running statistics after a training step."""
    torch.manual_seed(0)
    refiner = with_refiner(GGDNet(TINY)).refiner
    for module in refiner.points:
        if isinstance(module, torch.nn.BatchNorm1d):
            torch.nn.init.normal_(module.running_mean)
            torch.nn.init.uniform_(module.running_var, 0.5, 2.0)
            torch.nn.init.normal_(module.weight)
    torch.nn.init.normal_(refiner.out.weight, std=0.5)   # a refiner that says something
    partial, shape = torch.rand(3, 64, 3) - 0.5, box_shape([[4.5, 1.8, 1.5], [5.0, 2.0, 1.8], [12.0, 2.5, 3.5]])
    for _ in range(2):
        refiner.eval()
        with torch.no_grad():
            modules = refiner.vector(partial, shape)
        with torch.inference_mode():
            folded, one = refiner.vector(partial, shape), refiner.vector(partial[1:2], shape[1:2])
        assert refiner._fold.cached is not None and modules.abs().max() > 1e-3
        torch.testing.assert_close(folded, modules, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(one, modules[1:2], rtol=1e-5, atol=1e-6)
        refiner.train()   # moves the running statistics in place: the fold must follow
        refiner.vector(partial + 1.0, shape)
        assert refiner._fold.cached is None
