"""`gd-completion train`: generate (or load cached) synthetic vehicle scans and train GGD-Net."""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gd_completion.atomic import atomic_path, make_folder
from gd_completion.errors import DataFormatError
from gd_completion.synth.cache import MESH_FRACTION, DatasetSpec, cached_dataset
from gd_completion.synth.dataset import (
    V1_SAMPLING,
    V2_SAMPLING,
    SampleOptions,
)

if TYPE_CHECKING:
    from gd_completion.drive_frames import DriveSettings
    from gd_completion.model.config import GGDConfig
    from gd_completion.preprocess import Preprocessing

# torch, the model and the training loop are imported in the functions that use them: `--help` stays light.

log = logging.getLogger(__name__)

# Seeds of the validation set are offset so that they never meet the training seeds.
VALIDATION_SEED_OFFSET = 1_000_003


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("train", help="train GGD-Net on generated vehicle scans", description=__doc__)
    parser.add_argument("--output", type=Path, default=Path("runs/ggd"), help="run folder (last.pt, best.pt, log)")
    parser.add_argument("--samples", type=int, default=4000, help="training samples to generate (default 4000)")
    parser.add_argument("--val-samples", type=int, default=200, help="validation samples (default 200)")
    parser.add_argument("--seed", type=int, default=0, help="data and initialisation seed")
    parser.add_argument("--meshes", type=Path, default=None,
                        help="extra folder of vehicle meshes (.ply/.obj/.off/.glb) mixed with procedural shapes")
    parser.add_argument("--mesh-fraction", type=float, default=MESH_FRACTION,
                        help="with --meshes, the share 0-1 of the shapes drawn from the meshes, the rest procedural "
                        f"(default {MESH_FRACTION})")
    parser.add_argument("--cache", type=Path, default=None,
                        help="folder for the generated data sets (.npz), named after everything that shapes them "
                        "(generator version, seed, sizes, beam patterns, the meshes' contents); a file made with "
                        "the same settings is reused (default: --output)")
    parser.add_argument("--workers", type=int, default=2, help="processes generating data (default 2)")
    parser.add_argument("--epochs", type=int, default=70)
    parser.add_argument("--generation-epochs", type=int, default=40, help="epochs with lambda=0 (paper: 40)")
    parser.add_argument("--lam", type=float, default=3.0, help="lambda after the generation epochs (paper: 3)")
    parser.add_argument("--alpha", type=float, default=1000.0,
                        help="weight of the control-point smooth-L1 term (paper: 1000)")
    parser.add_argument("--beta", type=float, default=0.5, help="weight of the Laplacian shape term (paper: 0.5)")
    parser.add_argument("--gamma", type=float, default=0.0,
                        help="weight of the surface term: the unsquared distance of each output point to the nearest "
                        "ground-truth point, x100 (default 0: the paper's loss)")
    parser.add_argument("--surface-planes", action="store_true",
                        help="measure the surface term to the tangent plane of the nearest ground-truth point (fitted "
                        "to its 16 nearest) instead of to the point itself, so points within the targets' spacing "
                        "are still pulled onto the surface (needs --gamma > 0)")
    parser.add_argument("--rho", type=float, default=0.0,
                        help="weight of the repulsion term: output points closer than 0.03 (normalised) to their graph "
                        "neighbours pushed apart, x1000 (default 0: the paper's loss)")
    parser.add_argument("--tangential", action="store_true",
                        help="measure the repulsion term's distances within each point's plane (spread along the "
                        "surface, not off it)")
    parser.add_argument("--drive", default=None, metavar="FOLDER",
                        help="a labelled real drive (PandaSet layout) whose moving vehicles are added to every step: "
                        "each crop with the vehicle's multi-frame aggregate as a partial reference (only its coverage "
                        "counts); in a recipe an object of drive_frames.DriveSettings' fields")
    parser.add_argument("--drive-weight", type=float, default=1.0,
                        help="weight of the drive's batches in the loss (default 1)")
    parser.add_argument("--drive-precision", type=float, default=0.0,
                        help="weight of the drive's precision term within the drive's loss (so times --drive-weight "
                        "in the total): each output point's distance to the vehicle's aggregate, capped at "
                        "0.03 (normalised; losses.NEAR_REFERENCE) so points where the aggregate saw nothing feel no "
                        "pull, x100 (default 0: coverage only)")
    parser.add_argument("--gt-points", type=int, default=None,
                        help="points sampled on each ground-truth surface (default: the model's N_o); denser targets "
                        "make the nearest ground-truth point a closer stand-in for the surface")
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--lr-final", type=float, default=None,
                        help="cosine decay of the learning rate per epoch from --lr to this (default: constant)")
    parser.add_argument("--device", default=None, help="torch device (default: cuda when available, else cpu)")
    parser.add_argument("--time-budget", type=float, default=None, help="stop after this many seconds")
    parser.add_argument("--resume", action="store_true", help="continue from OUTPUT/last.pt")
    parser.add_argument("--num-control", type=int, default=None, help="N_c (default: GGDConfig's 256)")
    parser.add_argument("--config", type=Path, default=None, help="JSON file with GGDConfig fields")
    parser.add_argument("--init-from", type=Path, default=None,
                        help="warm start: copy every tensor of this checkpoint whose name and shape match")
    parser.add_argument("--init-skip", action="append", default=[], metavar="PREFIX",
                        help="with --init-from, keep tensors whose name starts with PREFIX fresh (repeatable)")
    parser.add_argument("--freeze", action="append", default=[], metavar="PREFIX",
                        help="keep the parameters whose name starts with PREFIX as they are (no gradient, batch "
                        "norms in eval mode; e.g. refiner. to fine-tune a refined network around its box refiner)")
    parser.add_argument("--sampling", default="v1", choices=sorted(SAMPLING_PRESETS),
                        help="synthetic sampling preset (v1: the shipped v1 model's data; v2: every kind, wider sizes, "
                        "five sensor families, detector-box noise; see synth.dataset.SampleOptions)")
    parser.add_argument("--recipe", type=Path, default=None,
                        help="JSON recipe of a run (see recipes/): its keys are this command's options that shape the "
                        "model (samples, seed, meshes, config, sampling, epochs, lr, init_from, ...); combine it only "
                        "with --output, --cache, --workers, --device, --time-budget and --resume")
    parser.set_defaults(func=run)
    RECIPE_DEFAULTS.update({k: parser.get_default(k) for k in RECIPE_KEYS})


#: Options a recipe may set (argparse destinations), and their command-line defaults.
RECIPE_KEYS = ("samples", "val_samples", "seed", "meshes", "mesh_fraction", "epochs", "generation_epochs", "lam",
               "alpha", "beta", "gamma", "surface_planes", "rho", "tangential", "drive", "drive_weight",
               "drive_precision", "gt_points", "batch_size", "lr", "lr_final", "num_control", "config", "init_from",
               "init_skip", "sampling", "freeze")
RECIPE_DEFAULTS: dict[str, Any] = {}
_PATH_KEYS = ("meshes", "init_from")
SAMPLING_PRESETS = {"v1": V1_SAMPLING, "v2": V2_SAMPLING}


def load_recipe(path: Path, keys: tuple[str, ...]) -> dict[str, Any]:
    """A recipe file's JSON object, whose keys are among `keys`, "name" and "notes"; DataFormatError otherwise."""
    try:
        recipe = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataFormatError(f"{path}: cannot read the recipe ({exc})") from exc
    if not isinstance(recipe, dict):
        raise DataFormatError(f"{path}: a recipe is a JSON object")
    unknown = sorted(set(recipe) - set(keys) - {"name", "notes"})
    if unknown:
        raise DataFormatError(f"{path}: unknown recipe keys {unknown}; expected some of {list(keys)}")
    return recipe


def apply_recipe(args: argparse.Namespace, recipe_path: Path) -> None:
    """Set `args` from a recipe file; a shaping option also given on the command line is an error (one source
    of truth per run). Relative paths in the recipe are relative to the current folder, like the CLI's."""
    recipe = load_recipe(recipe_path, RECIPE_KEYS)
    clashes = [k for k in recipe if k in RECIPE_KEYS and getattr(args, k) != RECIPE_DEFAULTS.get(k)]
    if clashes:
        raise DataFormatError(f"{recipe_path}: also given on the command line: {clashes}")
    for key in RECIPE_KEYS:
        if key in recipe:
            value = recipe[key]
            setattr(args, key, Path(value) if key in _PATH_KEYS and value is not None else value)


def sampling_options(value: str | dict[str, Any]) -> SampleOptions:
    """A preset name of SAMPLING_PRESETS or a dict of SampleOptions fields; DataFormatError for anything else."""
    if isinstance(value, dict):
        try:
            return SampleOptions.from_dict(value)
        except (TypeError, ValueError) as exc:
            raise DataFormatError(f"sampling options: {exc}") from exc
    if value not in SAMPLING_PRESETS:
        raise DataFormatError(f"unknown sampling preset {value!r}; expected one of {sorted(SAMPLING_PRESETS)}")
    return SAMPLING_PRESETS[value]


def drive_settings(value: str | dict[str, Any]) -> DriveSettings:
    """A drive folder or a dict of `drive_frames.DriveSettings` fields; DataFormatError for anything else."""
    from gd_completion.drive_frames import DriveSettings

    try:
        return DriveSettings.from_dict({"pandaset": value} if isinstance(value, str) else value)
    except (TypeError, ValueError) as exc:
        raise DataFormatError(f"drive: {exc}") from exc


def drive_data(drive: DriveSettings, n_input: int, preprocessing: Preprocessing) -> tuple[tuple, tuple]:
    """(training, validation) (partial, reference, box sizes) of a real drive's completion pairs."""
    from gd_completion.drive_frames import drive_pairs

    train, val = drive_pairs(drive, n_input=n_input, preprocessing=preprocessing).split(drive.val_share)
    log.info("drive %s: %d training pairs, %d validation pairs (%d and %d vehicles)", drive.pandaset, len(train),
             len(val), len(set(train.track.tolist())), len(set(val.track.tolist())))
    return (train.partial, train.reference, train.size), (val.partial, val.reference, val.size)


def load_config(args: argparse.Namespace) -> GGDConfig:
    """GGDConfig from --config JSON (or a recipe's inline dict) and --num-control (the tree decoder arity follows
    N_c); DataFormatError for a configuration that is not valid JSON or not a valid GGDConfig."""
    from gd_completion.model.config import GGDConfig

    try:
        if isinstance(args.config, dict):   # inline in a recipe
            fields = dict(args.config)
        else:
            fields = json.loads(Path(args.config).read_text()) if args.config else {}
        if args.num_control is not None:
            fields["num_control"] = args.num_control
            fields.setdefault("tree_arity", tree_arity_for(GGDConfig().num_output - args.num_control))
        return GGDConfig.from_dict(fields)
    except (TypeError, ValueError) as exc:   # json.JSONDecodeError is a ValueError
        where = "" if isinstance(args.config, dict) or not args.config else f" {args.config}"
        raise DataFormatError(f"model configuration{where}: {exc}") from exc


def tree_arity_for(n_points: int) -> list[int]:
    """A TopNet arity list (root split into 8, then small factors) whose product is `n_points`."""
    arity, rest = [8], n_points
    if rest % 8:
        raise ValueError(f"num_output - num_control = {n_points} must be a multiple of 8")
    rest //= 8
    for factor in (8, 4, 2, 7, 3, 5):
        while rest % factor == 0 and rest > 1:
            arity.append(factor)
            rest //= factor
    if rest > 1:
        arity.append(rest)
    return arity


def mesh_fraction(args: argparse.Namespace) -> float:
    """The run's share of mesh shapes (`--mesh-fraction`, recipe key `mesh_fraction`) as a float; DataFormatError for
    anything but a number in [0, 1], or for another share than the default without meshes."""
    value = args.mesh_fraction
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
        raise DataFormatError(f"mesh fraction {value!r} must be a number in [0, 1]")
    if args.meshes is None and value != RECIPE_DEFAULTS["mesh_fraction"]:
        raise DataFormatError("a mesh fraction without meshes (--meshes, recipe key meshes) draws nothing from them")
    return float(value)


def dataset_specs(args: argparse.Namespace, config: GGDConfig, options: SampleOptions
                  ) -> tuple[DatasetSpec, DatasetSpec]:
    """The training and validation data sets of a run (`args`: this command's options after its recipe; the mesh
    share checked, `mesh_fraction`)."""
    spec = DatasetSpec(args.samples, args.seed, config.num_input, args.gt_points or config.num_output, args.meshes,
                       mesh_fraction=mesh_fraction(args), options=options)
    return spec, dataclasses.replace(spec, n_samples=args.val_samples, seed=args.seed + VALIDATION_SEED_OFFSET)


def recipe_datasets(recipe: Path, cache: Path, workers: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """The training and validation data sets of training recipe `recipe`, loaded from `cache` when it holds
    them (`cached_dataset`), else generated there."""
    from gd_completion.cli import build_parser

    args = build_parser("train").parse_args(["train"])
    apply_recipe(args, recipe)
    spec, val_spec = dataset_specs(args, load_config(args), sampling_options(args.sampling))
    return cached_dataset(cache, "train", spec, workers), cached_dataset(cache, "val", val_spec, workers)


def run(args: argparse.Namespace) -> int:
    import torch

    from gd_completion.train import TrainSettings, train

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if args.recipe is not None:
        apply_recipe(args, args.recipe)
    options = sampling_options(args.sampling)   # a bad preset, configuration or setting fails before any folder
    drive = None if args.drive is None else drive_settings(args.drive)
    for name in ("drive_weight", "drive_precision"):
        if drive is None and getattr(args, name) != RECIPE_DEFAULTS[name]:
            raise DataFormatError(f"a {name.replace('_', ' ')} without a drive (--drive, recipe key drive) weighs "
                                  "nothing")
    config = load_config(args)
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    settings = TrainSettings(epochs=args.epochs, generation_epochs=args.generation_epochs, lam=args.lam,
                             alpha=args.alpha, beta=args.beta, gamma=args.gamma,
                             surface_planes=args.surface_planes, rho=args.rho,
                             tangential=args.tangential, drive_weight=args.drive_weight,
                             drive_precision=args.drive_precision,
                             batch_size=args.batch_size, lr=args.lr, lr_final=args.lr_final, seed=args.seed,
                             device=device, freeze=tuple(args.freeze),
                             time_budget_s=args.time_budget)
    spec, val_spec = dataset_specs(args, config, options)
    # a drive without usable vehicles fails before any folder or synthetic data
    drive_sets = None if drive is None else drive_data(drive, config.num_input, spec.preprocessing)
    make_folder(args.output)  # an unwritable output fails before any work
    cache = make_folder(args.cache or args.output)
    train_data = cached_dataset(cache, "train", spec, args.workers)
    val_data = cached_dataset(cache, "val", val_spec, args.workers)
    with atomic_path(args.output / "settings.json") as tmp:
        tmp.write_text(json.dumps(
            {"config": config.to_dict(), "settings": dataclasses.asdict(settings), "samples": args.samples,
             "val_samples": args.val_samples, "meshes": str(args.meshes) if args.meshes else None,
             "recipe": str(args.recipe) if args.recipe else None,
             "data": train_data["metadata"]["cache_key"],
             "init_from": str(args.init_from) if args.init_from else None, "init_skip": args.init_skip,
             "drive": dataclasses.asdict(drive) if drive else None}, indent=2))
    sized = config.box_conditioning   # a box-conditioned model is given the size of the box it sees
    result = train(config, (train_data["partial"], train_data["complete"]) + ((train_data["size"],) if sized else ()),
                   (val_data["partial"], val_data["complete"]) + ((val_data["size"],) if sized else ()),
                   args.output, settings, resume=args.resume,
                   init_from=args.init_from, init_skip=tuple(args.init_skip), preprocessing=spec.preprocessing,
                   drive=drive_sets)
    print(f"train: {result.epochs_done} epochs, best checkpoint {result.best_path}, last {result.last_path}")
    return 0
