"""`gd-completion evaluate`: baselines and GGD-Net on a held-out synthetic set and on PandaSet parked vehicles."""
from __future__ import annotations

import argparse
import importlib.util
import time
from dataclasses import replace
from pathlib import Path

from gd_completion.atomic import make_folder
from gd_completion.errors import EvaluationError
from gd_completion.preprocess import POOL_MARGIN, check_pool_margin

# torch, the model and the evaluation modules are imported in run_evaluation: `--help` stays light.

DEFAULT_PANDASET = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "pandaset-002"
DEFAULT_MESHES = DEFAULT_PANDASET.parent / "vehicle-meshes"


def run_evaluation(args: argparse.Namespace) -> int:
    """Run the parts selected by `args`, print the tables and write report.md and PNGs to args.output."""
    import torch

    from gd_completion.evaluation.box_noise import BoxNoise
    from gd_completion.evaluation.pandaset_eval import evaluate_pandaset, input_preprocessing, wider_margin
    from gd_completion.evaluation.report import (
        ablation_section,
        fusion_section,
        pandaset_section,
        synthetic_section,
        write_renders,
        write_report,
    )
    from gd_completion.evaluation.synthetic import (
        EVAL_SEED,
        control_point_ablation,
        evaluate_synthetic,
        load_heldout,
        load_heldout_meshes,
    )
    from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_checkpoint, read_checkpoint_metadata

    start = time.perf_counter()
    noise = None if args.no_box_noise else BoxNoise(*(args.box_noise or ()), seed=args.box_noise_seed)  # checked first
    classifying = args.synthetic_samples > 0 and not args.no_classification
    for name, value in (("--classifiers", args.classifiers), ("--classifier-epochs", args.classifier_epochs)):
        if value is not None and not classifying:
            raise EvaluationError(f"{name}: the classification part is skipped (--no-classification or "
                                  "--synthetic-samples 0)")
        if value is not None and value < 1:
            raise EvaluationError(f"{name} {value}: at least one")
    for name, value in (("--crop-margin", args.crop_margin), ("--pool-margin", args.pool_margin)):
        if value is not None and args.no_pandaset:
            raise EvaluationError(f"{name}: the PandaSet part is skipped (--no-pandaset)")
    try:   # the crop's own check
        pool_margin = POOL_MARGIN if args.pool_margin is None else check_pool_margin(args.pool_margin)
    except ValueError as error:
        raise EvaluationError(f"--pool-margin {args.pool_margin}: a margin in metres ({error})") from None
    synthetic_seed = EVAL_SEED if args.synthetic_seed is None else args.synthetic_seed
    if args.threads:
        torch.set_num_threads(args.threads)
    model_path = Path(args.model) if args.model else DEFAULT_WEIGHTS
    model, preprocessing = load_checkpoint(model_path)
    if args.crop_margin is not None:   # the contract's own checks, and only wider than it
        try:
            replace(preprocessing, crop_margin=args.crop_margin)
        except ValueError as error:
            raise EvaluationError(f"--crop-margin {args.crop_margin}: a margin in metres ({error})") from None
        if args.crop_margin < preprocessing.crop_margin:
            raise EvaluationError(f"--crop-margin {args.crop_margin}: narrower than the model's contract "
                                  f"({preprocessing.crop_margin} m)")
    input_margin = wider_margin(preprocessing, args.crop_margin)   # the PandaSet parts' (None: the contract's)
    out = make_folder(args.output)  # an unwritable output fails before the evaluation, not after it
    meta = {k: v for k, v in read_checkpoint_metadata(model_path).items()
            if k not in ("format", "format_version", "config") and isinstance(v, (str, int, float))}
    shown = model_path.resolve()
    shown = shown.relative_to(Path.cwd()) if shown.is_relative_to(Path.cwd()) else shown
    sections = [f"Model: `{shown}` (N_c = {model.config.num_control}, N_o = {model.config.num_output}, "
                f"{model.num_parameters():,} parameters"
                + "".join(f"; {k}: {v}" for k, v in meta.items()) + ")."]
    print(sections[0] + "\n", flush=True)
    timings: list[str] = []

    def emit(text: str) -> None:
        sections.append(text)
        print(text + "\n", flush=True)

    if args.synthetic_samples > 0:
        t0 = time.perf_counter()
        try:
            heldout = load_heldout(args.synthetic_samples, seed=synthetic_seed, path=args.synthetic_data)
            partial, complete = heldout.partial, heldout.complete
        except EvaluationError as error:
            emit(f"## Synthetic held-out set\n\nSkipped: {error}.")
        else:
            built = time.perf_counter() - t0
            result = evaluate_synthetic(model, partial, complete, heldout.sizes, seed=synthetic_seed,
                                        source=heldout.source, max_batch=args.max_batch, surface=heldout.surface,
                                        meshes=heldout.meshes)
            emit(synthetic_section(result))
            write_renders(out, "synthetic_vehicles.png", result.examples)
            if args.ablation_checkpoints:
                emit(ablation_section(control_point_ablation(args.ablation_checkpoints, partial, complete,
                                                             heldout.sizes, max_batch=args.max_batch), len(partial)))
            timings.append(f"synthetic: data {built:.1f} s, evaluation {time.perf_counter() - t0 - built:.1f} s")
    elif args.ablation_checkpoints:
        emit("## Control-point ablation\n\nSkipped: it needs the synthetic set (--synthetic-samples > 0).")

    if args.heldout_mesh_samples > 0 and args.synthetic_samples > 0:
        t0 = time.perf_counter()
        title = "Held-out meshes (synthetic scans of meshes never trained on)"
        try:
            meshes = load_heldout_meshes(args.heldout_mesh_samples, args.heldout_meshes or DEFAULT_MESHES,
                                         seed=synthetic_seed)
        except EvaluationError as error:
            emit(f"## {title}\n\nSkipped: {error}.")
        else:
            built = time.perf_counter() - t0
            result = evaluate_synthetic(model, meshes.partial, meshes.complete, meshes.sizes, seed=synthetic_seed,
                                        source=meshes.source, max_batch=args.max_batch, surface=meshes.surface,
                                        meshes=meshes.meshes)
            emit(synthetic_section(result, title))
            write_renders(out, "heldout_meshes.png", result.examples)
            timings.append(f"held-out meshes: data {built:.1f} s, evaluation {time.perf_counter() - t0 - built:.1f} s")

    if args.synthetic_samples > 0 and not args.no_classification:
        from gd_completion.evaluation.classification import (
            CLASSIFIERS,
            ClassifierSettings,
            classification_section,
            evaluate_classification,
        )

        t0 = time.perf_counter()
        classified = evaluate_classification(
            model, mesh_dir=args.heldout_meshes or DEFAULT_MESHES, preprocessing=preprocessing,
            pandaset=None if args.no_pandaset else (args.pandaset or DEFAULT_PANDASET),
            train_samples=args.classification_train_samples, synthetic_samples=args.classification_samples,
            mesh_samples=args.heldout_mesh_samples, sensors=tuple(args.sensors), max_vehicles=args.max_vehicles,
            classifiers=args.classifiers or CLASSIFIERS, max_batch=args.max_batch,
            settings=replace(ClassifierSettings(), epochs=args.classifier_epochs or ClassifierSettings.epochs))
        emit(classification_section(classified))
        steps = ", ".join(f"{k} {v:.1f} s" for k, v in classified.seconds.items())
        timings.append(f"classification: {time.perf_counter() - t0:.1f} s ({steps})")

    pandaset = Path(args.pandaset) if args.pandaset else DEFAULT_PANDASET
    if args.no_pandaset:
        pass
    elif not (pandaset / "lidar").is_dir():
        emit(f"## PandaSet\n\nSkipped: {pandaset} not found (give --pandaset DIR).")
    else:
        t0 = time.perf_counter()
        result = evaluate_pandaset(model, pandaset, preprocessing=preprocessing,
                                   max_frames_per_vehicle=args.max_frames_per_vehicle or None,
                                   max_vehicles=args.max_vehicles, max_batch=args.max_batch,
                                   sensors=tuple(args.sensors), random_points=args.random_reference_points,
                                   noise=noise, input_margin=input_margin, pool_margin=pool_margin)
        emit(pandaset_section(result, num_control=model.config.num_control, num_input=model.config.num_input))
        write_renders(out, "pandaset_vehicles.png", result.examples)
        write_renders(out, "pandaset_worst.png", result.worst)
        steps = ", ".join(f"{k} {v:.1f} s" for k, v in result.seconds.items())
        timings.append(f"pandaset: {time.perf_counter() - t0:.1f} s ({steps})")
        if args.no_fusion:
            pass
        elif importlib.util.find_spec("gd_completion.fusion") is None:
            emit("## PandaSet 002: track fusion\n\nSkipped: gd_completion.fusion is not installed.")
        else:
            from gd_completion.evaluation.fusion_eval import evaluate_fusion
            from gd_completion.fusion import FusionLimits, TrackFusion

            t0 = time.perf_counter()
            fused = evaluate_fusion(model, pandaset, preprocessing=preprocessing, max_frames=args.fusion_max_frames,
                                    consistency_frames=args.fusion_consistency_frames,
                                    max_vehicles=args.fusion_max_vehicles, max_batch=args.max_batch,
                                    input_margin=input_margin, pool_margin=pool_margin,
                                    fusion_factory=lambda: TrackFusion(
                                        FusionLimits(align=None) if args.no_fusion_align else FusionLimits()))
            emit(fusion_section(fused))
            steps = ", ".join(f"{k} {v:.1f} s" for k, v in fused.seconds.items())
            timings.append(f"fusion: {time.perf_counter() - t0:.1f} s ({steps})")
        if not args.no_reuse:
            from gd_completion.evaluation.reuse_eval import evaluate_reuse, reuse_section
            from gd_completion.limits import OFFLINE_LIMITS
            from gd_completion.pipeline import VehicleCompleter
            from gd_completion.reuse import ReuseSettings

            t0 = time.perf_counter()
            threads = torch.get_num_threads()
            inputs = input_preprocessing(preprocessing, input_margin)   # the completers crop as the node would
            reused = evaluate_reuse(pandaset, lambda ids, reuse: VehicleCompleter(
                model, preprocessing=inputs, limits=OFFLINE_LIMITS, track_ids=ids, pool_margin=pool_margin,
                reuse=ReuseSettings() if reuse else None), preprocessing=preprocessing, frames=args.reuse_frames,
                input_margin=input_margin)
            torch.set_num_threads(threads)
            emit(reuse_section(reused))
            steps = ", ".join(f"{k} {v:.1f} s" for k, v in reused.seconds.items())
            timings.append(f"reuse: {time.perf_counter() - t0:.1f} s ({steps})")

    timings.append(f"total {time.perf_counter() - start:.1f} s, {torch.get_num_threads()} torch threads")
    emit("## Run time\n\n" + "\n".join(f"- {t}" for t in timings))
    path = write_report(out, sections)
    print(f"wrote {path}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `evaluate`."""
    parser = subparsers.add_parser("evaluate", help="evaluate completion on synthetic and PandaSet data",
                                   description=__doc__)
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped weights)")
    parser.add_argument("--output", default="evaluation_report",
                        help="folder for report.md and PNGs (default ./evaluation_report)")
    parser.add_argument("--synthetic-samples", type=int, default=128,
                        help="held-out synthetic pairs (default 128; 0 skips the synthetic part)")
    parser.add_argument("--synthetic-seed", type=int, default=None,
                        help="seed of the held-out set (default: evaluation.synthetic.EVAL_SEED, reserved for "
                        "evaluation: never train or validate on it)")
    parser.add_argument("--heldout-meshes", default=None,
                        help=f"mesh folder holding synth.meshio.HELDOUT_MESHES, never trained on (default "
                        f"{DEFAULT_MESHES}; skipped if absent)")
    parser.add_argument("--heldout-mesh-samples", type=int, default=128,
                        help="synthetic pairs made from the held-out meshes (default 128; 0 skips them, as does "
                        "--synthetic-samples 0)")
    parser.add_argument("--synthetic-data", default=None, help="prebuilt held-out set (synth load_dataset)")
    parser.add_argument("--ablation-checkpoints", nargs="+", default=None, metavar="PT",
                        help="checkpoints of the control-point ablation (e.g. N_c = 128, 256, 512)")
    parser.add_argument("--pandaset", default=None,
                        help=f"PandaSet sequence folder (default {DEFAULT_PANDASET}; skipped if absent)")
    parser.add_argument("--no-pandaset", action="store_true", help="skip the PandaSet part")
    parser.add_argument("--max-frames-per-vehicle", type=int, default=0,
                        help="evenly spaced observations (frame, sensor) per vehicle (default 0 = all)")
    parser.add_argument("--sensors", type=int, nargs="+", default=[0, 1], choices=[0, 1],
                        help="PandaSet sensors (0 Pandar64, 1 PandarGT; default both)")
    parser.add_argument("--random-reference-points", type=int, default=20_000,
                        help="points of the random PandaSet reference (default 20000)")
    noise = parser.add_mutually_exclusive_group()
    noise.add_argument("--no-box-noise", action="store_true", help="skip the PandaSet box-noise run")
    noise.add_argument("--box-noise", type=float, nargs=4, default=None,
                        metavar=("CENTRE_XY", "CENTRE_Z", "SIZE", "YAW_DEG"),
                        help="standard deviations of the box-noise run: centre x/y and z (m), size (a fraction of "
                        "each dimension), yaw (deg); default 0.15 0.05 0.05 4. Set your detector's errors, or one "
                        "kind alone (0.15 0 0 0: centre errors only)")
    parser.add_argument("--box-noise-seed", type=int, default=2024, help="seed of the box noise (default 2024)")
    parser.add_argument("--max-vehicles", type=int, default=None, help="first N stationary vehicles only")
    parser.add_argument("--crop-margin", type=float, default=None, metavar="METRES",
                        help="crop margin of the PandaSet parts' inputs (single frames with exact and noisy boxes, "
                             "track fusion, completion reuse; default: the checkpoint's contract; only wider): the "
                             "node's crop_margin; the references and the classification part keep the contract's")
    parser.add_argument("--pool-margin", type=float, default=None, metavar="METRES",
                        help="margin of the measured points the merge publishes beside the crop, not fed to the "
                             "network, in the PandaSet parts (single frames with exact and noisy boxes, track "
                             f"fusion, completion reuse; default {POOL_MARGIN}, the node's pool_margin; 0: the "
                             "crop's points only); the classification part keeps the default")
    parser.add_argument("--no-fusion", action="store_true", help="skip the PandaSet track-fusion part")
    parser.add_argument("--no-reuse", action="store_true", help="skip the PandaSet completion-reuse part")
    parser.add_argument("--reuse-frames", type=int, default=None,
                        help="first N frames of the sequence in the completion-reuse part (default all)")
    parser.add_argument("--fusion-max-frames", type=int, default=None,
                        help="first N frames of each vehicle fed to the track fusion (default all)")
    parser.add_argument("--fusion-consistency-frames", type=int, default=10,
                        help="first N frames of each vehicle in the consistency metric (default 10)")
    parser.add_argument("--no-fusion-align", action="store_true",
                        help="track fusion without aligning each frame to its track (the node's fusion_align:=false)")
    parser.add_argument("--fusion-max-vehicles", type=int, default=None,
                        help="first N stationary and N moving vehicles in the fusion part (default all)")
    parser.add_argument("--no-classification", action="store_true",
                        help="skip the downstream classification part (as does --synthetic-samples 0)")
    parser.add_argument("--classification-train-samples", type=int, default=2400,
                        help="complete shapes the part's PointNet classifier trains on (default 2400)")
    parser.add_argument("--classifiers", type=int, default=None,
                        help="classifiers trained (seeds in a row) and averaged in the classification part (default "
                             "3: one classifier's accuracy moves by several points with its seed; about 5 minutes "
                             "each on one core)")
    parser.add_argument("--classifier-epochs", type=int, default=None,
                        help="epochs of each classifier's training (default 8)")
    parser.add_argument("--classification-samples", type=int, default=330,
                        help="procedural held-out shapes it classifies (default 330; the held-out meshes follow "
                        "--heldout-mesh-samples, PandaSet --pandaset)")
    parser.add_argument("--max-batch", type=int, default=32, help="vehicles per forward pass (default 32)")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (default: torch's choice)")
    parser.set_defaults(func=run_evaluation)
