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
the evaluation; the gaps come from them) and the stationary ones (the evaluation's), noisy and annotated boxes.

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


def crops(sequence: PandaSetSequence, vehicles: dict[str, str], frames: list[int], noisy: bool) -> list[Crop]:
    """The vehicles' crops of `frames` (both sensors), with their annotated or noisy boxes."""
    prep = replace(Preprocessing(), min_points=1)
    out = []
    for track in collect_tracks(sequence, vehicles, prep, frames=frames, sensors=SENSORS, noise=BoxNoise()).values():
        for k, truth in enumerate(track.boxes):
            crop = track.noisy[k]
            if crop is None or len(track.points[k]) < MIN_INPUT_POINTS:
                continue
            points, box = (crop.normalized, crop.box) if noisy else (track.points[k], truth)
            if len(points) < MIN_INPUT_POINTS:
                continue
            sensor = normalize(np.asarray(track.origins[k], np.float64)[None], box)[0]
            out.append(Crop(np.asarray(points, np.float64), box, truth, sensor))
    return out


def face_gaps(annotated: list[Crop]) -> tuple[float, float]:
    """Median distance (metres) between a face seen head-on and its outermost point, along and across the box."""
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
    return float(np.median(gaps[0])), float(np.median(gaps[1]))


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


@torch.inference_mode()
def refiner_centre(model: GGDNet, crop: Crop) -> np.ndarray:
    """(2,) centre offset (metres, box axes) of the model's box refiner."""
    assert model.refiner is not None
    points = torch.from_numpy(network_input(crop.points.astype(np.float32), model.config.num_input))[None]
    vector = model.refiner.vector(points, box_shape([crop.box.size]))[0].double().numpy()
    return vector[:2] * crop.box.size[0]


def rms_errors(model: GGDNet, rows: list[Crop], gaps: tuple[float, float]) -> dict[str, np.ndarray]:
    """Per estimate, the RMS error (metres) of the centre along and across the box."""
    errors: dict[str, list[np.ndarray]] = {"given": [], "refiner": [], "faces": [], "mean": []}
    for crop in rows:
        truth = true_frame(crop.truth, crop.box)[:2].astype(np.float64) * crop.box.size[0]
        refined, faces = refiner_centre(model, crop), faces_centre(crop, gaps)
        for name, estimate in (("given", np.zeros(2)), ("refiner", refined), ("faces", faces),
                               ("mean", (refined + faces) / 2)):
            errors[name].append(estimate - truth)
    return {name: np.sqrt(np.mean(np.square(e), axis=0)) for name, e in errors.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default=str(DEFAULT_WEIGHTS))
    parser.add_argument("--pandaset", default="../shared/data/pandaset-002")
    parser.add_argument("--every", type=int, default=4, help="every Nth frame of the drive (default 4)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = load_model(args.model).eval()
    sequence = PandaSetSequence(args.pandaset)
    frames = list(sequence.frame_indices())[::args.every]
    moving, parked = moving_vehicles(sequence, SENSORS), stationary_vehicles(sequence, SENSORS)
    gaps = face_gaps(crops(sequence, moving, frames, noisy=False))
    print(f"face gaps (median, moving vehicles' annotated boxes): along {gaps[0]:.3f} m, across {gaps[1]:.3f} m")
    print("RMS centre error along / across the box (m)")
    print(f"{'vehicles':<11}{'boxes':<10}{'crops':>6}" + "".join(f"{n:>16}" for n in ("given", "refiner", "faces",
                                                                                        "mean")))
    for kind, vehicles in (("moving", moving), ("stationary", parked)):
        for noisy in (True, False):
            rows = crops(sequence, vehicles, frames, noisy)
            errors = rms_errors(model, rows, gaps)
            print(f"{kind:<11}{'noisy' if noisy else 'annotated':<10}{len(rows):>6}"
                  + "".join(f"{e[0]:>9.3f} / {e[1]:.3f}" for e in errors.values()))


if __name__ == "__main__":
    main()
