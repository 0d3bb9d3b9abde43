"""Many bags completed (`gd-completion complete` with several inputs): one output bag per input, resumable,
in this process or on Ray."""
from __future__ import annotations

import glob
import logging
import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

from gd_completion.errors import BagError, GDCompletionError
from gd_completion.progress import progress_bar
from gd_completion.settings import CompletionSettings

ENGINES = ("local", "ray")
MANIFEST_SUFFIXES = (".txt", ".list")
BAG_SUFFIXES = (".mcap", ".db3")


@dataclass(frozen=True)
class BagJob:
    """One input bag and its output bag."""

    src: Path
    out: Path

    @property
    def name(self) -> str:
        return self.out.name


@dataclass
class BagOutcome:
    """What happened to one bag: `done` (with the summary text), `skipped` (output exists) or `failed` (reason)."""

    job: BagJob
    status: str
    detail: str = ""
    frames: int = 0
    seconds: float = 0.0

    def line(self) -> str:
        """One summary line naming the bag."""
        return f"{self.status} {self.job.src} -> {self.job.out}: {self.detail}"


def is_manifest(path: str | Path) -> bool:
    """A text file listing bags (`.txt`, `.list`), not a bag."""
    return Path(path).suffix.lower() in MANIFEST_SUFFIXES and Path(path).is_file()


def _is_glob(text: str) -> bool:
    return any(c in text for c in "*?[") and not Path(text).exists()


def is_single_bag(inputs: list[str]) -> bool:
    """One input that is neither a glob nor a manifest: `complete IN OUT` writes the bag OUT (today's behaviour)."""
    return len(inputs) == 1 and not _is_glob(inputs[0]) and not is_manifest(inputs[0])


def read_manifest(path: str | Path) -> list[Path]:
    """Bag paths of a manifest, one per line; `#` starts a comment; relative paths are taken from its folder."""
    manifest = Path(path)
    try:
        lines = manifest.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise BagError(f"{manifest}: cannot read manifest: {error}") from error
    bags = []
    for line in lines:
        text = line.split("#", 1)[0].strip()
        if text:
            bag = Path(text).expanduser()
            bags.append(bag if bag.is_absolute() else manifest.parent / bag)
    return bags


def expand_inputs(inputs: list[str]) -> list[Path]:
    """Bag paths from bag paths, globs (sorted) and manifests, in order, each once."""
    bags: list[Path] = []
    for text in inputs:
        if _is_glob(text):
            matches = sorted(glob.glob(text))
            if not matches:
                raise BagError(f"{text}: no bag matches")
            bags.extend(Path(m) for m in matches)
        elif is_manifest(text):
            bags.extend(read_manifest(text))
        else:
            bags.append(Path(text))
    return list(dict.fromkeys(bags))


def output_name(bag: Path) -> str:
    """The output bag's name: the input folder's name, or the file's stem for a `.mcap`/`.db3` file."""
    return bag.stem if bag.suffix.lower() in BAG_SUFFIXES else bag.name


def plan_jobs(inputs: list[str], out_dir: str | Path) -> list[BagJob]:
    """One job per input bag, output `out_dir/<input name>`; two inputs with one output name are refused."""
    jobs = [BagJob(bag, Path(out_dir) / output_name(bag)) for bag in expand_inputs(inputs)]
    if not jobs:
        raise BagError("no input bags")
    seen: dict[Path, Path] = {}
    for job in jobs:
        if job.out in seen:
            raise BagError(f"{seen[job.out]} and {job.src} would both write {job.out}; rename one of them")
        seen[job.out] = job.src
    return jobs


def remove_partials(out: Path) -> None:
    """Remove the temporaries a killed run left beside `out` (the bag writer's `.<name>.*.partial` folders)."""
    for stale in out.parent.glob(f".{glob.escape(out.name)}.*.partial"):
        shutil.rmtree(stale, ignore_errors=True)


def _outcome(job: BagJob, run: Callable[[], Any]) -> BagOutcome:
    """Run one bag's completion; a bad bag gives a failed outcome with the reason instead of an exception."""
    try:
        summary = run()
    except GDCompletionError as error:
        return BagOutcome(job, "failed", str(error))
    except OSError as error:
        return BagOutcome(job, "failed", f"{error.filename or job.src}: {error.strerror or error}")
    return BagOutcome(job, "done", summary.text(), summary.frames, summary.seconds)


def _local(jobs: list[BagJob], workers: int, settings: CompletionSettings,
           bag_options: dict[str, Any]) -> Iterator[BagOutcome]:
    """Bags one after the other in this process; their frames on one shared FramePool of `workers` processes."""
    from gd_completion.bags.completion import complete_bag
    from gd_completion.frame_pool import FramePool

    with FramePool(workers, settings) as pool:
        for job in jobs:
            yield _outcome(job, partial(complete_bag, job.src, job.out, settings, pool=pool, progress=False,
                                        **bag_options))


class BagWorker:
    """A Ray actor: one completer (loaded once), completing whole bags with it."""

    def __init__(self, settings: CompletionSettings) -> None:
        self.settings = settings
        self.error: GDCompletionError | None = None
        self.completer = None
        try:
            from gd_completion.pipeline import VehicleCompleter

            self.completer = VehicleCompleter.from_settings(settings)
        except GDCompletionError as error:
            self.error = error

    def complete(self, job: BagJob, bag_options: dict[str, Any]) -> BagOutcome:
        from gd_completion.bags.completion import complete_bag

        if self.error is not None:
            return BagOutcome(job, "failed", str(self.error))
        return _outcome(job, lambda: complete_bag(job.src, job.out, self.settings, completer=self.completer,
                                                  progress=False, **bag_options))


def ray_resources(device: str, threads: int) -> dict[str, float]:
    """What one worker asks Ray for: its torch threads as CPUs, and one GPU when the device is CUDA."""
    return {"num_cpus": max(threads, 1), "num_gpus": 1 if device.startswith("cuda") else 0}


def _ray(jobs: list[BagJob], workers: int, settings: CompletionSettings, bag_options: dict[str, Any],
         address: str | None) -> Iterator[BagOutcome]:
    """One Ray actor per worker (model loaded once each), one actor call per bag; results as they finish."""
    import ray

    started = not ray.is_initialized()
    if started:
        if address:
            ray.init(address=address, logging_level=logging.WARNING)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, logging_level=logging.WARNING)
    try:
        threads = settings.num_threads or 1
        resources = ray_resources(settings.device, threads)
        # Ray gives each actor its GPU as CUDA_VISIBLE_DEVICES, so inside the actor it is always cuda (device 0).
        settings = replace(settings, num_threads=threads, device="cuda" if resources["num_gpus"] else settings.device)
        actor: Any = ray.remote(num_cpus=resources["num_cpus"], num_gpus=resources["num_gpus"])(BagWorker)
        pool = [actor.remote(settings) for _ in range(min(workers, len(jobs)))]
        pending: dict[Any, tuple[Any, BagJob]] = {}
        queue = list(jobs)
        for worker in pool:
            if queue:
                job = queue.pop(0)
                pending[worker.complete.remote(job, bag_options)] = (worker, job)
        while pending:
            [ref], _ = ray.wait(list(pending), num_returns=1)
            worker, job = pending.pop(ref)
            try:
                outcome = ray.get(ref)
            except ray.exceptions.RayError as error:  # the worker died (out of memory, killed): this bag failed
                outcome = BagOutcome(job, "failed", f"{job.src}: Ray worker failed: {error}")
                worker = actor.remote(settings)
            yield outcome
            if queue:
                job = queue.pop(0)
                pending[worker.complete.remote(job, bag_options)] = (worker, job)
    finally:
        if started:
            ray.shutdown()


def complete_many(jobs: list[BagJob], settings: CompletionSettings | None = None, *, engine: str = "local",
                  workers: int = 1, address: str | None = None, overwrite: bool = False, progress: bool = True,
                  report: Callable[[BagOutcome], None] | None = None, **bag_options: Any) -> list[BagOutcome]:
    """Complete every job's bag; bags whose output exists are skipped (unless `overwrite`), so a rerun resumes.

    A bag that fails is reported (`failed`, with the reason) and the others go on. `engine` 'local' runs the bags
    in this process, frames on `workers` processes; 'ray' runs one bag per Ray actor call on `workers` actors
    (a local Ray with `workers` CPUs, or the cluster at `address`). Output bags are the same for both engines.
    `report(outcome)` is called as each bag ends; outcomes come back in the order of `jobs`. `settings`: as
    `complete_bag`'s (default `CompletionSettings.offline()`); `bag_options`: its other keyword arguments.
    """
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    settings = settings or CompletionSettings.offline()
    outcomes: dict[BagJob, BagOutcome] = {}
    todo = []
    for job in jobs:
        if job.out.exists() and not overwrite:
            outcomes[job] = BagOutcome(job, "skipped", "output exists")
        else:
            remove_partials(job.out)
            todo.append(job)
    bag_options = {**bag_options, "overwrite": overwrite}
    with progress_bar("complete", "bags", total=len(jobs), quiet=not progress) as bar:
        bar.update(len(jobs) - len(todo))
        if todo:
            run = (_ray(todo, workers, settings, bag_options, address) if engine == "ray"
                   else _local(todo, workers, settings, bag_options))
            for outcome in run:
                outcomes[outcome.job] = outcome
                if report is not None:
                    report(outcome)
                bar.update(1)
    return [outcomes[job] for job in jobs]


def summary_text(outcomes: list[BagOutcome], seconds: float) -> str:
    """The last line: bags done, skipped and failed, frames and rate."""
    counts = {s: sum(o.status == s for o in outcomes) for s in ("done", "skipped", "failed")}
    frames = sum(o.frames for o in outcomes)
    rate = frames / seconds if seconds > 0 else 0.0
    return (f"{len(outcomes)} bags: {counts['done']} completed, {counts['skipped']} skipped (output exists), "
            f"{counts['failed']} failed; {frames} frames ({rate:.2f} frames/s, {seconds:.1f} s)")

