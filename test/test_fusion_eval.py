"""Track-fusion evaluation: the consistency metric by hand, a short PandaSet run with a tiny model, the command."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from test_evaluation import TINY

from gd_completion.evaluation import fusion_eval
from gd_completion.model import GGDNet
from gd_completion.spacing import SHIPPED_SPACING


def _pts(*rows):
    return np.array(rows, dtype=np.float32)


class ConcatFusion:
    """Test double of TrackFusion: every frame of a track so far, oldest first (boxes of parked cars agree)."""

    def __init__(self):
        self.history = {}

    def update(self, stamp_ns, vehicles):
        out = []
        for v in vehicles:
            frames = self.history.setdefault(v.box.instance_id, [])
            frames.append(v.normalized)
            out.append(replace(v, normalized=np.concatenate(frames)))
        return out


def test_consistency_hand_computed():
    a = _pts([0, 0, 0], [1, 0, 0])
    b = _pts([0, 0, 0], [0, 2, 0])
    c = _pts([5, 5, 5], [6, 6, 6])
    # frames 3 -> 4 consecutive: a->b 0.5, b->a 2.0 -> 2.5 ; 4 -> 6 is not a consecutive pair
    assert fusion_eval.consistency([a, b, c], [3, 4, 6]) == pytest.approx([2.5])
    # b -> c: b->c: (0,0,0)->(5,5,5) 75, (0,2,0)->(5,5,5) 59 -> 67 ; c->b: (5,5,5)->(0,2,0) 59, (6,6,6)->(0,2,0) 88
    assert fusion_eval.consistency([a, b, c], [3, 4, 5]) == pytest.approx([2.5, 67 + 73.5])
    assert fusion_eval.consistency([a, a], [1, 2]) == [0.0]
    assert fusion_eval.consistency([a], [1]) == []


def test_library_oracle_picks_the_best_stretched_shape():
    rng = np.random.default_rng(0)
    truth = rng.uniform(-0.5, 0.5, (40, 3)).astype(np.float32) * np.array([1, 0.4, 0.3], np.float32)
    measured = truth[truth[:, 1] > 0.1][:3]
    size = (4.0, 1.6, 1.2)
    # the same shape stored for a box twice as long (normalised: y and z halved): stretched back to `size`
    stored = truth * np.array([1, 0.5, 0.5], np.float32)
    other = truth + np.float32(0.05)
    n = 2 * len(measured) + len(truth)   # nothing thinned away
    for library in ([(other, size), (stored, (8.0, 1.6, 1.2))], [(stored, (8.0, 1.6, 1.2)), (other, size)]):
        assert fusion_eval.library_oracle(truth, measured, size, library, n) == pytest.approx(0.0, abs=1e-9)
    wrong = fusion_eval.library_oracle(truth, measured, size, [(other, size)], n)
    assert wrong > 1e-4
    assert wrong <= fusion_eval.coverage_error(truth, other).item() + 1e-9   # the measured points only help
    assert math.isnan(fusion_eval.library_oracle(truth, measured, size, [], n))
    # thinned to fewer points than the truth has, the exact shape can no longer cover it exactly
    thinned = fusion_eval.library_oracle(truth, measured, size, [(stored, (8.0, 1.6, 1.2))], 8)
    assert 0 < thinned < fusion_eval.coverage_error(truth, truth[:1]).item()


def _fusions():
    yield pytest.param(ConcatFusion, id="concat-double")
    try:
        from gd_completion.fusion import TrackFusion
    except ModuleNotFoundError:
        yield pytest.param(None, id="TrackFusion", marks=pytest.mark.skip("gd_completion.fusion not present"))
    else:
        yield pytest.param(TrackFusion, id="TrackFusion")


@pytest.mark.parametrize("factory", list(_fusions()))
def test_fusion_evaluation_on_a_few_pandaset_frames(shared_data, factory):
    root = shared_data / "pandaset-002"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    torch.manual_seed(0)
    result = fusion_eval.evaluate_fusion(GGDNet(TINY).eval(), root, frames=range(0, 8), max_frames=8,
                                         consistency_frames=4, max_vehicles=2, fusion_factory=factory,
                                         reference_points=1024)
    assert result.n_stationary == 2 and result.max_frames == 8
    rows = {r.k: r for r in result.coverage}
    assert list(rows) == list(fusion_eval.FUSED_FRAMES)
    assert rows[10].n_vehicles == 0 and math.isnan(rows[10].raw_fused)  # only 8 frames fused
    for k in (1, 2, 5, 0):
        r = rows[k]
        assert r.n_vehicles >= 1
        assert math.isfinite(r.raw_fused) and r.raw_fused >= 0
        assert math.isfinite(r.fused_completion) and r.fused_completion > 0
        if r.n_single:
            assert math.isfinite(r.single_completion) and r.single_completion > 0
            # adding every fused point can only bring the reference closer: never worse than the completion alone
            assert r.single_with_fused <= r.single_completion + 1e-9 and r.measured_bound <= 1.0 + 1e-9
            # the library oracle only at k = 5: the other chosen stationary vehicle's points beside the fused points
            assert math.isfinite(r.library_oracle) == (k == fusion_eval.RATIO_FRAMES)
            assert r.prior_fused > 0 and r.prior_single > 0 and math.isfinite(r.prior_ratio)
    # one frame fused: the fused partial is that frame (TrackFusion voxel-thins it), so both completions agree but
    # for that thinning
    assert rows[1].fused_completion_single == pytest.approx(rows[1].single_completion, rel=0.1)
    assert rows[1].ratio == pytest.approx(1.0, rel=0.1)
    tolerance = 1e-5 if factory is ConcatFusion else 0.1
    assert rows[1].prior_ratio == pytest.approx(1.0, rel=tolerance)   # the prior on the same points: the same
    # more frames of a parked car cover more of its aggregate
    raw = [rows[k].raw_fused for k in (1, 2, 5, 0)]
    assert raw[0] > raw[-1]
    assert all(later <= earlier * 1.05 for earlier, later in zip(raw, raw[1:]))
    if factory is ConcatFusion:
        assert all(later <= earlier + 1e-9 for earlier, later in zip(raw, raw[1:]))  # supersets: never worse
        assert raw[-1] == 0.0  # all 8 frames fused = the aggregate the reference is sampled from
        if rows[0].n_single:   # so the completion with every fused point added covers the reference exactly
            assert rows[0].single_with_fused == pytest.approx(0.0, abs=1e-6)   # x1e3 scale; distances by GEMM
            assert rows[0].measured_bound < 1e-5
        # no cap (the default): every frame given is fused, here the same 8
        torch.manual_seed(0)
        uncapped = fusion_eval.evaluate_fusion(GGDNet(TINY).eval(), root, frames=range(0, 8), consistency_frames=4,
                                               max_vehicles=2, fusion_factory=factory, reference_points=1024)
        assert uncapped.max_frames is None
        assert [r.raw_fused for r in uncapped.coverage if r.n_vehicles] == [r.raw_fused for r in result.coverage
                                                                             if r.n_vehicles]
    stationary = result.consistency[0]
    assert stationary.group == "stationary" and stationary.n_pairs >= 1
    assert math.isfinite(stationary.single) and math.isfinite(stationary.fused) and stationary.single > 0
    assert math.isfinite(stationary.single_network) and stationary.single_network != stationary.single


def test_fused_and_single_partials_are_both_scored_through_the_published_merge(shared_data, monkeypatch):
    root = shared_data / "pandaset-002"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    calls = []
    scored = fusion_eval.published_outputs

    def recording(model, partials, sizes=None, max_batch=32, asides=None, spacing=None):
        calls.append((len(partials), len(asides), spacing))
        return scored(model, partials, sizes, max_batch=max_batch, asides=asides, spacing=spacing)

    monkeypatch.setattr(fusion_eval, "published_outputs", recording)
    torch.manual_seed(0)
    fusion_eval.evaluate_fusion(GGDNet(TINY).eval(), root, frames=range(0, 3), max_frames=3, consistency_frames=2,
                                max_vehicles=1, reference_points=256)
    # the fused partials, then the frames alone, each with its frame's ground band (pooled as the pipeline does),
    # evenly spaced as the pipeline's default
    assert len(calls) == 2 and all(count == bands > 0 for count, bands, _ in calls)
    assert all(spacing == SHIPPED_SPACING for *_, spacing in calls)


def test_fusion_section_text():
    from gd_completion.evaluation.report import fusion_section

    cov = [fusion_eval.CoverageRow(k, 3, 2.0 / (k or 20), 0.5, 2, 0.3, 0.6, 0.45) for k in fusion_eval.FUSED_FRAMES]
    cons = [fusion_eval.ConsistencyRow("stationary", 3, 10, 0.8, 0.2, 0.5, 0.2),
            fusion_eval.ConsistencyRow("moving", 2, 5, 1.0, 0.9)]
    cov = [replace(r, library_oracle=0.42, prior_fused=0.4, prior_single=0.5) if r.k == 5 else r for r in cov]
    text = fusion_section(fusion_eval.FusionResult(cov, cons, 20, 10, None, 3, 2, {}))
    assert "## PandaSet 002: track fusion" in text and "| all (<= 20) |" in text
    assert "Target (a)/(c) <= 0.60 at k = 5: 0.500, met. The fused measurements alone, added in full, give " \
        "(d)/(c) = 0.750 there; with the best-matching other vehicle's points, (e)/(c) = 0.700." in text
    assert "| (d) (c) + raw fused | (d)/(c) | (e) library oracle | (e)/(c) |" in text
    assert "| 0.420              | 0.700   |" in text and "| -                  | -       |" in text
    prior_table = text[text.index("### Beside the box-only prior"):]
    row_5 = next(line for line in prior_table.splitlines() if line.startswith("| 5 "))
    assert [c.strip() for c in row_5.strip("|").split("|")] == ["5", "2", "0.300", "0.600", "0.500", "0.400", "0.500",
                                                               "0.800"]
    assert "stationary 0.250 (met; without the merge 0.400), moving 0.900 (not met; without the merge nan)" in text
    assert "first 20 frames of each vehicle" in text and "first 10 frames" in text
    every = fusion_section(fusion_eval.FusionResult(cov, cons, None, 10, None, 3, 2, {}))
    assert "every frame of each vehicle fused" in every and "| all |" in every and "all (<=" not in every


def test_evaluate_no_fusion_skips_the_section(tmp_path, shared_data):
    import argparse

    from gd_completion.model import save_checkpoint
    from gd_completion.tools import evaluate

    root = shared_data / "pandaset-002"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    model_path = save_checkpoint(tmp_path / "tiny.pt", GGDNet(TINY))
    parser = argparse.ArgumentParser()
    evaluate.register(parser.add_subparsers())
    args = parser.parse_args(["evaluate", "--model", str(model_path), "--output", str(tmp_path / "out"),
                              "--synthetic-samples", "0", "--pandaset", str(root), "--max-vehicles", "1",
                              "--max-frames-per-vehicle", "1", "--no-fusion", "--no-reuse",
                              "--threads", "1"])
    assert args.func(args) == 0
    text = (tmp_path / "out" / "report.md").read_text()
    assert "## PandaSet 002: single frame" in text and "track fusion" not in text


def test_a_wider_input_crop_feeds_the_fusion_and_keeps_the_contracts_references(shared_data):
    """`input_margin`: what the fusion is fed is cropped wider (as the node's crop_margin), the references, the
    points counted and so the vehicle-frames scored stay the contract's; narrower than the contract is refused."""
    root = shared_data / "pandaset-002"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    plain = fusion_eval.fuse_drive(root, frames=range(0, 5), fusion_factory=ConcatFusion)
    wide = fusion_eval.fuse_drive(root, frames=range(0, 5), fusion_factory=ConcatFusion, input_margin=0.4)
    assert set(wide.tracks) == set(plain.tracks) and plain.tracks
    more = 0
    for i, track in plain.tracks.items():
        other = wide.tracks[i]
        assert other.frames == track.frames
        for p in range(len(track.frames)):
            np.testing.assert_array_equal(other.references[p], track.single[p])   # the contract's crop
            assert track.references[p] is track.single[p]
            assert len(other.single[p]) >= len(track.single[p])
            more += len(other.single[p]) > len(track.single[p])
            assert other.usable(p) == track.usable(p)
            # the fusion got the wide crops: the concatenating double's partial is every wide frame so far
            assert len(other.fused[p]) == sum(len(s) for s in other.single[:p + 1])
        np.testing.assert_array_equal(other.aggregate(), track.aggregate())
    assert more > 0
    with pytest.raises(ValueError, match="narrower than the contract"):
        fusion_eval.fuse_drive(root, frames=range(0, 2), input_margin=0.05)
    # a box whose points all lie beyond the contract's crop is not fed at all (these frames hold such boxes at 2 m)
    sequence = fusion_eval.PandaSetSequence(root)
    uuids = set(fusion_eval.vehicle_tracks(sequence))
    prep = fusion_eval.Preprocessing(min_points=1)
    loaded = fusion_eval.load_frames(sequence, uuids, prep, frames=range(0, 5), input_margin=2.0)
    wider = 0
    for _, inputs, references in loaded:
        assert [v.box.instance_id for v in inputs] == [v.box.instance_id for v in references]
        wider += sum(len(i.normalized) > len(r.normalized) for i, r in zip(inputs, references))
    assert wider > 0
    unfiltered = fusion_eval.load_frames(sequence, uuids, replace(prep, crop_margin=2.0), frames=range(0, 5))
    assert sum(len(v) for _, v, _ in unfiltered) > sum(len(v) for _, v, _ in loaded)   # such boxes exist here


@pytest.mark.integration  # reads the shared drive at length
def test_completion_reuse_scores_a_wider_input_crop_on_the_same_vehicle_frames(shared_data):
    """evaluate_reuse(input_margin=): the same vehicle-frames and references, the baseline fed the wider crops,
    and the report says so."""
    from gd_completion.evaluation.reuse_eval import evaluate_reuse, reuse_section
    from gd_completion.pipeline import VehicleCompleter
    from gd_completion.preprocess import Preprocessing
    from gd_completion.reuse import ReuseSettings

    root = shared_data / "pandaset-002"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    torch.manual_seed(0)
    model = GGDNet(TINY).eval()
    results = {}
    for margin in (None, 0.4):
        prep = Preprocessing(crop_margin=0.1 if margin is None else margin)
        results[margin] = evaluate_reuse(root, lambda ids, reuse, prep=prep: VehicleCompleter(
            model, preprocessing=prep, track_ids=ids, reuse=ReuseSettings() if reuse else None),
            frames=3, input_margin=margin)
    plain, wide = results[None], results[0.4]
    assert wide.input_margin == 0.4 and plain.input_margin is None
    assert (wide.vehicle_frames, wide.coverage_items) == (plain.vehicle_frames, plain.coverage_items)
    assert plain.coverage_items > 0
    assert wide.rows[-1].coverage != plain.rows[-1].coverage   # the baseline saw the wider crops
    assert "cropped with a margin of 0.4 m" in reuse_section(wide)
    assert "cropped with a margin" not in reuse_section(plain)
