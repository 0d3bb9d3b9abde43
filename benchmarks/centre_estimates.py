"""How well is a vehicle's centre known from its scan? The box refiner against a geometric estimate from the seen faces.

On PandaSet-002 (every fourth frame, both sensors), each vehicle crop with at least MIN_INPUT_POINTS points is taken
with its annotated box and with a noisy one (`evaluation.box_noise`, the evaluation's sigmas and seed), and the true
box's centre is estimated in that box's frame by

- `given`: the box itself (no correction);
- `refiner`: the model's box refiner (`model.box_refiner`, what the published completion uses);
- `faces`: per axis of the box, the seen faces of the scan: where the robust extent of the points (1st to 99th
  percentile) spans at least 90 % of the box's size, its middle; else the face towards the sensor, half the box's
  size inwards from the extreme point plus a gap (the median distance between that face and its outermost point,
  measured on the moving vehicles' annotated boxes); else (the sensor beside that extent) no correction; nor where
  the correction exceeds MAX_SHIFT;
- `mean`: the mean of the refiner's and the faces' estimates.

Printed: the RMS error of the centre along and across the box (metres), for the moving vehicles (never scored by
the evaluation; the gaps come from them) and the stationary ones (the evaluation's), noisy and annotated boxes; and
the RMS heading error (degrees) of the given box, the refiner and an L-shape search (the closeness criterion of
Zhang et al. 2017 over +-10 deg in steps of 0.5 deg).

    python benchmarks/centre_estimates.py [--model PT] [--pandaset DIR] [--every N]
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, replace

import numpy as np
import torch

from gd_completion.datasets.pandaset import PandaSetSequence
from gd_completion.drive_frames import moving_vehicles, true_frame
from gd_completion.evaluation.box_noise import BoxNoise
from gd_completion.evaluation.pandaset_eval import MIN_INPUT_POINTS, SENSORS, collect_tracks, stationary_vehicles
from gd_completion.geometry import Box3D, normalize
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.model.network import GGDNet, box_shape
from gd_completion.preprocess import Preprocessing, network_input

QUANTILE = 1.0      # robust extremes: the 1st and 99th percentiles of the points along an axis
FULL_SPAN = 0.9     # an extent of at least this share of the box's size: both faces seen
MAX_SHIFT = 0.6     # metres: a larger correction (4 sigma of the evaluation's centre noise) is not trusted


@dataclass(frozen=True)
class Crop:
    """One crop: its points normalised by `box` (annotated or noisy), the true box and the sensor's position."""

    points: np.ndarray
    box: Box3D
    truth: Box3D
    sensor: np.ndarray   # (3,) in `box`'s normalised frame


def crops(sequence: PandaSetSequence, vehicles: dict[str, str], frames: list[int]) -> dict[bool, list[Crop]]:
    """The vehicles' crops of `frames` (both sensors), read once: by noisy (True) or annotated (False) box."""
    prep = replace(Preprocessing(), min_points=1)
    out: dict[bool, list[Crop]] = {True: [], False: []}
    for track in collect_tracks(sequence, vehicles, prep, frames=frames, sensors=SENSORS, noise=BoxNoise()).values():
        for k, truth in enumerate(track.boxes):
            crop = track.noisy[k]
            if crop is None or len(track.points[k]) < MIN_INPUT_POINTS:
                continue
            for noisy, (points, box) in ((True, (crop.normalized, crop.box)), (False, (track.points[k], truth))):
                if len(points) >= MIN_INPUT_POINTS:
                    sensor = normalize(np.asarray(track.origins[k], np.float64)[None], box)[0]
                    out[noisy].append(Crop(np.asarray(points, np.float64), box, truth, sensor))
    return out


def face_gaps(annotated: list[Crop]) -> tuple[np.ndarray, np.ndarray]:
    """10th, 50th and 90th percentiles of the distance (metres) between a face seen head-on and its outermost point,
    along and across the box."""
    gaps: tuple[list[float], list[float]] = ([], [])
    for crop in annotated:
        metres = crop.points[:, :2] * crop.box.size[0]
        sensor = crop.sensor[:2] * crop.box.size[0]
        for axis, half in ((0, crop.box.size[0] / 2), (1, crop.box.size[1] / 2)):
            lo, hi = np.percentile(metres[:, axis], [QUANTILE, 100 - QUANTILE])
            if hi - lo < FULL_SPAN * 2 * half:
                if sensor[axis] > hi:
                    gaps[axis].append(half - hi)
                elif sensor[axis] < lo:
                    gaps[axis].append(lo + half)
    along, across = (np.percentile(g, [10, 50, 90]) if g else np.full(3, np.nan) for g in gaps)
    return along, across


def faces_centre(crop: Crop, gaps: tuple[float, float]) -> np.ndarray:
    """(2,) centre offset (metres, box axes) from the seen faces (see the module)."""
    metres = crop.points[:, :2] * crop.box.size[0]
    sensor = crop.sensor[:2] * crop.box.size[0]
    centre = np.zeros(2)
    for axis, half in ((0, crop.box.size[0] / 2), (1, crop.box.size[1] / 2)):
        lo, hi = np.percentile(metres[:, axis], [QUANTILE, 100 - QUANTILE])
        if hi - lo >= FULL_SPAN * 2 * half:
            centre[axis] = (lo + hi) / 2
        elif sensor[axis] > hi:
            centre[axis] = hi + gaps[axis] - half
        elif sensor[axis] < lo:
            centre[axis] = lo - gaps[axis] + half
    return np.where(np.abs(centre) <= MAX_SHIFT, centre, 0.0)


def lshape_yaw(crop: Crop, max_deg: float = 10.0, step_deg: float = 0.5, floor: float = 0.02) -> float:
    """Heading offset (rad) of the candidate whose rotated points lie closest to the edges of their extent."""
    xy = crop.points[:, :2] * crop.box.size[0]
    angles = np.radians(np.arange(-max_deg, max_deg + 1e-9, step_deg))[:, None]
    c, s = np.cos(angles), np.sin(angles)
    along, across = c * xy[:, 0] + s * xy[:, 1], -s * xy[:, 0] + c * xy[:, 1]

    def to_edge(v: np.ndarray) -> np.ndarray:
        lo, hi = np.percentile(v, [QUANTILE, 100 - QUANTILE], axis=1)
        return np.minimum(np.abs(v - lo[:, None]), np.abs(hi[:, None] - v))

    score = (1.0 / np.maximum(np.minimum(to_edge(along), to_edge(across)), floor)).sum(1)
    return float(angles[int(np.argmax(score)), 0])


@torch.inference_mode()
def refiner_vector(model: GGDNet, crop: Crop) -> np.ndarray:
    """(7,) `BoxFrame` vector of the model's box refiner."""
    assert model.refiner is not None
    points = torch.from_numpy(network_input(crop.points.astype(np.float32), model.config.num_input))[None]
    return model.refiner.vector(points, box_shape([crop.box.size]))[0].double().numpy()


def rms_errors(model: GGDNet, rows: list[Crop], gaps: tuple[float, float]
               ) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Per estimate, the RMS error (metres) of the centre along and across the box; per heading estimate its RMS
    error (degrees)."""
    errors: dict[str, list[np.ndarray]] = {"given": [], "refiner": [], "faces": [], "mean": []}
    headings: dict[str, list[float]] = {"given": [], "refiner": [], "L-shape": []}
    for crop in rows:
        truth = true_frame(crop.truth, crop.box).astype(np.float64)
        centre = truth[:2] * crop.box.size[0]
        vector = refiner_vector(model, crop)
        refined, faces = vector[:2] * crop.box.size[0], faces_centre(crop, gaps)
        for name, estimate in (("given", np.zeros(2)), ("refiner", refined), ("faces", faces),
                               ("mean", (refined + faces) / 2)):
            errors[name].append(estimate - centre)
        for name, yaw in (("given", 0.0), ("refiner", float(vector[3])), ("L-shape", lshape_yaw(crop))):
            headings[name].append(yaw - float(truth[3]))
    return ({name: np.sqrt(np.mean(np.square(e), axis=0)) for name, e in errors.items()},
            {name: float(np.degrees(np.sqrt(np.mean(np.square(h))))) for name, h in headings.items()})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default=str(DEFAULT_WEIGHTS))
    parser.add_argument("--pandaset", default="../shared/data/pandaset-002")
    parser.add_argument("--every", type=int, default=4, help="every Nth frame of the drive (default 4)")
    args = parser.parse_args()
    if args.every < 1:
        parser.error("--every must be >= 1")
    torch.set_num_threads(1)
    model = load_model(args.model).eval()
    sequence = PandaSetSequence(args.pandaset)
    frames = list(sequence.frame_indices())[::args.every]
    groups = {"moving": crops(sequence, moving_vehicles(sequence, SENSORS), frames),
              "stationary": crops(sequence, stationary_vehicles(sequence, SENSORS), frames)}
    spread = face_gaps(groups["moving"][False])
    gaps = (float(spread[0][1]), float(spread[1][1]))   # the medians
    print("face gaps, moving vehicles' annotated boxes (10th / 50th / 90th percentile, m): along "
          + " / ".join(f"{g:.3f}" for g in spread[0]) + ", across " + " / ".join(f"{g:.3f}" for g in spread[1]))
    print("RMS centre error along / across the box (m)")
    print(f"{'vehicles':<11}{'boxes':<10}{'crops':>6}" + "".join(f"{n:>16}" for n in ("given", "refiner", "faces",
                                                                                        "mean"))
          + "   heading RMS (deg): given / refiner / L-shape")
    for kind, by_box in groups.items():
        for noisy in (True, False):
            rows = by_box[noisy]
            errors, headings = rms_errors(model, rows, gaps)
            print(f"{kind:<11}{'noisy' if noisy else 'annotated':<10}{len(rows):>6}"
                  + "".join(f"{e[0]:>9.3f} / {e[1]:.3f}" for e in errors.values())
                  + "   " + " / ".join(f"{h:.2f}" for h in headings.values()))


if __name__ == "__main__":
    main()
