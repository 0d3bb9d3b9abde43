"""`gd-completion train-refiner`: train the box refiner of a GGD-Net checkpoint on the data sets of training recipes."""
from __future__ import annotations

import argparse
import json
import logging
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gd_completion.atomic import atomic_path, make_folder
from gd_completion.errors import DataFormatError

if TYPE_CHECKING:
    from gd_completion.drive_frames import DriveSettings
    from gd_completion.train_refiner import FrameData, RefinerSettings

# Keys of a refiner recipe (recipes/box_refiner*.json) besides "name" and "notes": the base checkpoint, the
# training recipes whose data sets it uses, and fields of train_refiner.RefinerSettings.
SETTING_KEYS = ("epochs", "batch_size", "lr", "seed", "norm_train_epochs", "widths", "hidden")
RECIPE_KEYS = ("base", "data", "drive", *SETTING_KEYS)   # drive: drive_frames.DriveSettings' fields


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("train-refiner", help="train the box refiner of a GGD-Net checkpoint",
                                   description=__doc__)
    parser.add_argument("--recipe", type=Path, required=True,
                        help="JSON recipe: base (a box-conditioned checkpoint), data (training recipes whose data "
                        "sets, made with box noise, are used: training and validation sets), epochs, batch_size, "
                        "lr, seed, norm_train_epochs, widths and hidden (the refiner's layer widths); optional drive: "
                        "{pandaset: a labelled drive (PandaSet layout, sensors 0 and 1) whose moving vehicles are "
                        "added, each crop with its box and with draws (default 4) noisy boxes, sigma_scale (the "
                        "evaluation's sigmas times 0.8 to 1.4), seed (7001), val_share (vehicles held out for "
                        "validation, 0.2)}")
    parser.add_argument("--output", type=Path, default=None, help="run folder (default runs/<recipe name>)")
    parser.add_argument("--cache", type=Path, default=Path("runs/cache"),
                        help="folder of the data sets (`gd-completion train --cache`; missing ones are generated)")
    parser.add_argument("--workers", type=int, default=2, help="processes generating missing data (default 2)")
    parser.add_argument("--device", default="cpu", help="torch device (default cpu)")
    parser.add_argument("--resume", action="store_true", help="continue from OUTPUT/last.pt")
    parser.set_defaults(func=run)


def read_recipe(path: Path) -> dict[str, Any]:
    """The recipe's keys, checked; DataFormatError naming the file otherwise."""
    from gd_completion.tools.train import load_recipe

    recipe = load_recipe(path, RECIPE_KEYS)
    missing = [k for k in ("base", "data") if k not in recipe]
    if missing:
        raise DataFormatError(f"{path}: missing recipe keys {missing}")
    if not isinstance(recipe["data"], list) or not recipe["data"]:
        raise DataFormatError(f"{path}: data must be a non-empty list of training recipes")
    if "drive" in recipe:
        recipe["drive"] = drive_settings(recipe["drive"], path)
    return recipe


def drive_settings(values: Any, path: Path) -> DriveSettings:
    """A recipe's `drive`, checked (before any data is made); DataFormatError naming the recipe otherwise."""
    from gd_completion.drive_frames import DriveSettings

    try:
        drive = DriveSettings.from_dict(values)
    except (TypeError, ValueError) as exc:
        raise DataFormatError(f"{path}: drive: {exc}") from exc
    if drive.ground_band:
        raise DataFormatError(f"{path}: drive: ground_band applies to completion training only; leave it out of a "
                              "refiner recipe")
    return drive


def drive_data(drive: DriveSettings, n_input: int, base: Path) -> tuple[FrameData, FrameData]:
    """(training, validation) refiner data of a recipe's labelled drive, cropped through the `base` checkpoint's
    preprocessing contract and brought to `n_input` points (the synthetic sets' input size)."""
    from gd_completion.drive_frames import drive_frames
    from gd_completion.model.checkpoint import read_checkpoint
    from gd_completion.preprocess import Preprocessing
    from gd_completion.train_refiner import FrameData

    preprocessing = Preprocessing.from_dict(read_checkpoint(base).get("preprocessing"))
    train, val = drive_frames(drive, n_input=n_input, preprocessing=preprocessing).split(drive.val_share)
    return FrameData.from_drive(train), FrameData.from_drive(val)


def recipe_settings(recipe: dict[str, Any], path: Path, device: str = "cpu") -> RefinerSettings:
    """The recipe's `RefinerSettings`, its refiner sizes checked; DataFormatError naming the file otherwise."""
    from gd_completion.model.config import GGDConfig
    from gd_completion.train_refiner import RefinerSettings

    try:
        settings = RefinerSettings(**{k: recipe[k] for k in SETTING_KEYS if k in recipe}, device=device)
        GGDConfig(box_conditioning=True, box_refinement=True, refiner_widths=settings.widths,
                  refiner_hidden=settings.hidden)
    except (TypeError, ValueError) as exc:
        raise DataFormatError(f"{path}: {exc}") from exc
    return settings


def run(args: argparse.Namespace) -> int:
    from gd_completion.tools.train import recipe_datasets
    from gd_completion.train_refiner import FrameData, train_refiner

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    recipe = read_recipe(args.recipe)
    settings = recipe_settings(recipe, args.recipe, args.device)   # before any data is generated
    output = make_folder(args.output or Path("runs") / recipe.get("name", args.recipe.stem))
    cache = make_folder(args.cache)
    sets = [recipe_datasets(Path(r), cache, args.workers) for r in recipe["data"]]
    train, val = FrameData.from_datasets([t for t, _ in sets]), FrameData.from_datasets([v for _, v in sets])
    if "drive" in recipe:
        drive_train, drive_val = drive_data(recipe["drive"], train.partial.shape[1], Path(recipe["base"]))
        train, val = FrameData.concat([drive_train, train]), FrameData.concat([drive_val, val])
    with atomic_path(output / "settings.json") as tmp:
        tmp.write_text(json.dumps({"recipe": str(args.recipe), **recipe}, indent=2, default=asdict))
    result = train_refiner(Path(recipe["base"]), train, val, output, settings, resume=args.resume)
    print(f"train-refiner: {result.epochs_done} epochs, best checkpoint {result.best_path}, last {result.last_path}")
    return 0
