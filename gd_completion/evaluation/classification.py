"""Completion for classification: a PointNet trained on complete vehicle shapes classifies partial scans,
completions and priors (the downstream experiment of the Graph-Guided Deformation paper, on vehicle classes)."""
from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from gd_completion.model.network import GGDNet
from gd_completion.preprocess import Preprocessing, with_aside

from .baselines import published_outputs
from .priors import prior_outputs
from .report import markdown_table

#: Classes of the experiment, in the classifier's output order.
CLASSES: tuple[str, ...] = ("car", "suv", "pickup", "van", "truck", "bus", "construction", "trailer")

#: Class of every procedural kind of `synth.vehicles.VEHICLE_KINDS`: sedans and hatchbacks are cars, pickups with
#: or without a load pickups, box trucks and articulated lorries (tractor and semi-trailer) trucks; a trailer
#: (car or box trailer without a cab, `Towed Object` on PandaSet) is its own class.
KIND_CLASSES: dict[str, str] = {
    "sedan": "car", "hatchback": "car", "suv": "suv", "pickup": "pickup", "pickup_load": "pickup", "van": "van",
    "box_truck": "truck", "semi_trailer": "truck", "bus": "bus", "construction": "construction",
    "trailer": "trailer",
}

#: Class of every mesh of `../shared/data/vehicle-meshes` (file stem), from its name and the manifest's category:
#: taxis, police and sports cars are cars, the ambulance a van; the buses have toy proportions (about
#: 4.1-4.6 x 1.8 x 1.7-2.2 m) but are buses. Held out (`synth.meshio.HELDOUT_MESHES`, never trained on):
#: basic_simplecarshort, basic_taxi, realistic_normalcar2, realistic_sportscar2 (car), realistic_cop_suv (suv),
#: public_schoolbus (bus).
MESH_CLASSES: dict[str, str] = {
    "basic_basiccar": "car", "basic_copcar": "car", "basic_racecar": "car", "basic_simplecarhigh": "car",
    "basic_simplecarshort": "car", "basic_taxi": "car", "public_ambulance": "van", "public_bus": "bus",
    "public_schoolbus": "bus", "public_taxi": "car", "realistic_cop": "car", "realistic_cop_suv": "suv",
    "realistic_normalcar1": "car", "realistic_normalcar2": "car", "realistic_sportscar": "car",
    "realistic_sportscar2": "car", "realistic_suv": "suv", "realistic_taxi": "car",
}

#: Classes counted right for a PandaSet label. PandaSet's `Car` holds SUVs too; it has no van class and puts
#: delivery and step vans under `Medium-sized Truck`. Labels not listed (Emergency Vehicle, Other Vehicle -
#: Uncommon, Motorcycle, ...) are left out of the experiment.
PANDASET_CLASSES: dict[str, tuple[str, ...]] = {
    "Car": ("car", "suv"), "Pickup Truck": ("pickup",), "Medium-sized Truck": ("truck", "van"),
    "Semi-truck": ("truck",), "Bus": ("bus",), "Other Vehicle - Construction Vehicle": ("construction",),
    "Towed Object": ("trailer",),
}

#: Inputs classified, in report order: the raw partial scan, the mirror + template prior, GGD-Net's P_o evenly spaced,
#: what the pipeline publishes (that after the measured merge) and the upper bound (complete shape or aggregate).
INPUT_NAMES: tuple[str, ...] = ("input", "mirror_template", "ggd", "ggd_merge", "complete")
INPUT_TITLES: dict[str, str] = {"input": "raw partial input", "mirror_template": "mirror + template prior",
                                "ggd": "GGD-Net (network output, evenly spaced)",
                                "ggd_merge": "GGD-Net published (measured merge)",
                                "complete": "complete shape (PandaSet: multi-frame aggregate)"}
#: Seed of the classifier's training shapes (below evaluation.synthetic.EVAL_SEED: never an evaluation seed).
TRAIN_SEED = 4_242_000
#: Offset from EVAL_SEED of the procedural held-out set (V2 sampling: every kind, box noise, sensor effects).
HELDOUT_SEED_OFFSET = 1
CLASSIFIER_POINTS = 1024
AGGREGATE_POINTS = 2048
MAX_OBSERVATIONS = 3   # PandaSet observations per vehicle, evenly spaced
CALIBRATION_SHAPES = 512   # training shapes that re-estimate the batch-norm statistics after training
#: Classifiers trained (seeds seed, seed + 1, ...) and averaged: one classifier's accuracy on the 128 held-out-mesh
#: scans moves by several points with its seed alone (docs/QUALITY.md).
CLASSIFIERS = 3
#: Seed of the validation shapes, drawn like the training shapes: the classifier's own check, no evaluation set.
VALIDATION_SEED = TRAIN_SEED + 1000


def class_index(name: str) -> int:
    """Index of a class of CLASSES."""
    return CLASSES.index(name)


def mesh_names(mesh_dir: str | Path, *, heldout: bool = False) -> list[str]:
    """File stems of the meshes of `mesh_dir` in the order `synth.dataset.build_dataset` numbers them ("mesh:<i>"):
    the training meshes (HELDOUT_MESHES left out, its default), or with `heldout` the held-out meshes only."""
    from gd_completion.synth.meshio import HELDOUT_MESHES, mesh_files

    return [p.stem for p in mesh_files(mesh_dir) if (p.stem in HELDOUT_MESHES) == heldout]


def sample_classes(kinds: Sequence[str] | np.ndarray, meshes: Sequence[str] = ()) -> np.ndarray:
    """(S,) int64 class indices of `build_dataset` samples from their `kind` (a procedural kind or "mesh:<i>",
    `meshes[i]` the mesh's file stem, see `mesh_names`)."""
    names = [MESH_CLASSES[meshes[int(k[5:])]] if str(k).startswith("mesh:") else KIND_CLASSES[str(k)] for k in kinds]
    return np.array([class_index(n) for n in names], np.int64)


def pandaset_classes(label: str) -> tuple[str, ...]:
    """Classes counted right for a PandaSet label (empty for labels outside the experiment)."""
    return PANDASET_CLASSES.get(label, ())


class PointNetClassifier(nn.Module):
    """PointNet: a shared MLP 3-64-128-256 on every point (batch norm, ReLU), max pool, 256-128-classes with
    dropout. Input (B, N, 3) in the normalised box frame, output logits (B, classes)."""

    def __init__(self, num_classes: int = len(CLASSES), dropout: float = 0.3) -> None:
        super().__init__()
        widths = (3, 64, 128, 256)
        layers: list[nn.Module] = []
        for a, b in zip(widths[:-1], widths[1:]):
            layers += [nn.Conv1d(a, b, 1, bias=False), nn.BatchNorm1d(b), nn.ReLU()]
        self.features = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Linear(256, 128, bias=False), nn.BatchNorm1d(128), nn.ReLU(),
                                  nn.Dropout(dropout), nn.Linear(128, num_classes))

    def forward(self, points: Tensor) -> Tensor:
        return self.head(self.features(points.transpose(1, 2)).amax(dim=2))


@dataclass(frozen=True)
class ClassifierSettings:
    """Classifier training: `epochs` over the shapes in batches of `batch_size`, Adam with a cosine schedule
    from `lr`; each step takes a random subset of `n_points` points per shape, scales each axis by
    U(1 - scale, 1 + scale), adds N(0, jitter) noise (clipped at 3 sigma) and mirrors y -> -y half the time
    (no rotation: the box frame fixes the heading)."""

    epochs: int = 8   # validation shapes of seed 4242001: 0.950-0.958 after 3 epochs, 0.985-0.993 after 8 (QUALITY.md)
    batch_size: int = 32
    lr: float = 2e-3
    weight_decay: float = 1e-4
    n_points: int = CLASSIFIER_POINTS
    jitter: float = 0.005
    scale: float = 0.06
    dropout: float = 0.3


@dataclass(frozen=True)
class ClassifierLog:
    """What trained the classifier: shapes per class, seed, settings, run time and the last epoch's loss and
    accuracy on its (augmented) training batches."""

    n_shapes: int
    counts: dict[str, int]
    seed: int
    settings: ClassifierSettings
    seconds: float
    loss: float
    accuracy: float
    source: str = ""


def _augment(clouds: np.ndarray, rng: np.random.Generator, settings: ClassifierSettings) -> np.ndarray:
    """(B, n_points, 3) float32: a random point subset of each (B, M, 3) cloud, scaled, jittered, maybe mirrored."""
    b, m = clouds.shape[:2]
    n = min(settings.n_points, m)
    rows = np.argsort(rng.random((b, m)), axis=1)[:, :n]
    out = np.take_along_axis(clouds, rows[..., None], axis=1)
    out = out * rng.uniform(1 - settings.scale, 1 + settings.scale, (b, 1, 3))
    out = out + np.clip(rng.normal(0.0, settings.jitter, out.shape), -3 * settings.jitter, 3 * settings.jitter)
    out[..., 1] *= np.where(rng.random(b) < 0.5, -1.0, 1.0)[:, None]
    return out.astype(np.float32)


@torch.no_grad()
def _calibrate_batch_norm(net: PointNetClassifier, clouds: np.ndarray, settings: ClassifierSettings, seed: int) -> None:
    """Batch-norm statistics re-estimated as plain averages over `clouds` (subsampled, not augmented), dropout
    off: the running averages of a short training lag behind its last weights."""
    norms = [m for m in net.modules() if isinstance(m, nn.BatchNorm1d)]
    net.eval()
    for m in norms:
        m.reset_running_stats()
        m.momentum = None   # cumulative average
        m.train()
    batch = fixed_count(clouds, settings.n_points, seed)
    for start in range(0, len(batch), settings.batch_size):
        if len(batch[start:start + settings.batch_size]) >= 2:
            net(torch.from_numpy(batch[start:start + settings.batch_size]))
    for m in norms:
        m.momentum = 0.1
    net.eval()


def train_classifier(clouds: np.ndarray, labels: np.ndarray, *, settings: ClassifierSettings = ClassifierSettings(),
                     seed: int = 0, source: str = "") -> tuple[PointNetClassifier, ClassifierLog]:
    """A PointNetClassifier trained on complete shapes `clouds` (S, M, 3) of classes `labels` (S,) (indices of
    CLASSES); deterministic for `seed` on the CPU (same thread count). Its batch-norm statistics are then
    re-estimated on up to CALIBRATION_SHAPES of the shapes. Returned in eval mode."""
    t0 = time.perf_counter()
    clouds = np.asarray(clouds, np.float32)
    labels = np.asarray(labels, np.int64)
    if clouds.ndim != 3 or clouds.shape[-1] != 3 or len(clouds) != len(labels) or len(clouds) < 2:
        raise ValueError(f"train_classifier: clouds {clouds.shape} and labels {labels.shape} do not match")
    rng = np.random.default_rng(seed)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        net = PointNetClassifier(len(CLASSES), settings.dropout)
        steps_per_epoch = -(-len(clouds) // settings.batch_size)
        optimizer = torch.optim.Adam(net.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, max(1, settings.epochs * steps_per_epoch))
        loss_sum, right = 0.0, 0
        for _ in range(settings.epochs):
            net.train()
            order = rng.permutation(len(clouds))
            loss_sum, right = 0.0, 0
            for start in range(0, len(order), settings.batch_size):
                batch = order[start:start + settings.batch_size]
                if len(batch) < 2:   # batch norm needs two shapes
                    continue
                logits = net(torch.from_numpy(_augment(clouds[batch], rng, settings)))
                target = torch.from_numpy(labels[batch])
                loss = nn.functional.cross_entropy(logits, target)
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                schedule.step()
                loss_sum += float(loss.detach()) * len(batch)
                right += int((logits.argmax(1) == target).sum())
        _calibrate_batch_norm(net, clouds[rng.permutation(len(clouds))[:CALIBRATION_SHAPES]], settings,
                              int(rng.integers(2**31)))
    counts = Counter(CLASSES[i] for i in labels)
    log = ClassifierLog(len(clouds), {c: counts[c] for c in CLASSES if counts[c]}, seed, settings,
                   time.perf_counter() - t0, loss_sum / len(clouds), right / len(clouds), source)
    return net.eval(), log


def fixed_count(clouds: Sequence[np.ndarray] | np.ndarray, n: int = CLASSIFIER_POINTS, seed: int = 0) -> np.ndarray:
    """(S, n, 3) float32: each cloud brought to `n` points, a random subset (seeded) of a larger cloud, the cloud
    repeated cyclically for a smaller one (max pooling ignores repeats)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((len(clouds), n, 3), np.float32)
    for i, cloud in enumerate(clouds):
        cloud = np.asarray(cloud, np.float32).reshape(-1, 3)
        if len(cloud) == 0:
            raise ValueError(f"fixed_count: cloud {i} is empty")
        rows = rng.choice(len(cloud), n, replace=False) if len(cloud) > n else np.arange(n) % len(cloud)
        out[i] = cloud[rows]
    return out


@torch.inference_mode()
def classify(classifier: PointNetClassifier, clouds: Sequence[np.ndarray] | np.ndarray,
             n_points: int = CLASSIFIER_POINTS, seed: int = 0, max_batch: int = 64) -> np.ndarray:
    """(S,) int64 predicted class indices of normalised clouds of any size (`fixed_count` to `n_points`)."""
    batch = fixed_count(clouds, n_points, seed)
    classifier = classifier.eval()
    preds = [classifier(torch.from_numpy(batch[s:s + max_batch])).argmax(1).numpy()
             for s in range(0, len(batch), max_batch)]
    return np.concatenate(preds).astype(np.int64) if preds else np.zeros(0, np.int64)


@dataclass(frozen=True)
class LabelledSet:
    """Observations to classify: normalised partial inputs (any size) with their boxes' sizes (S, 3) (length,
    width, height; m), an upper-bound cloud each (complete shape or aggregate), the label shown per observation
    (`truth`) and the classes counted right for it (`accepted`, (S, len(CLASSES)) bool); real scans also the
    points their crops kept aside (`preprocess.CroppedVehicle.aside`: measured, not fed to the network, pooled by the
    merge)."""

    name: str
    source: str
    partials: list[np.ndarray]
    sizes: np.ndarray
    complete: list[np.ndarray]
    truth: list[str]
    accepted: np.ndarray
    upper_bound: str = "complete shapes"
    asides: list[np.ndarray] | None = None


def _one_hot(labels: np.ndarray) -> np.ndarray:
    return np.eye(len(CLASSES), dtype=bool)[np.asarray(labels, np.int64)]


def training_shapes(n_samples: int, *, seed: int = TRAIN_SEED, mesh_dir: str | Path | None = None
                    ) -> tuple[np.ndarray, np.ndarray, str]:
    """(complete shapes (S, 2048, 3), class indices (S,), description) of `build_dataset(n_samples, seed,
    options=V2_SAMPLING)` with the training meshes of `mesh_dir` (30 %; HELDOUT_MESHES left out)."""
    from gd_completion.synth.dataset import V2_SAMPLING, build_dataset

    from .synthetic import EVAL_SEED

    if seed >= EVAL_SEED:
        raise ValueError(f"training seed {seed}: seeds from {EVAL_SEED} up are reserved for evaluation")
    data = build_dataset(n_samples, seed, meshes_dir=mesh_dir, options=V2_SAMPLING, n_input=256)
    meshes = mesh_names(mesh_dir) if mesh_dir is not None else []
    where = f"build_dataset({n_samples}, seed={seed}, V2 sampling" + \
        (f", {len(meshes)} training meshes)" if meshes else ", procedural)")
    return np.asarray(data["complete"], np.float32), sample_classes(data["kind"], meshes), where


def synthetic_set(n_samples: int, *, seed: int | None = None, mesh_dir: str | Path | None = None) -> LabelledSet:
    """Held-out pairs with their classes: without `mesh_dir`, procedural shapes of every kind with V2 sampling
    (seed EVAL_SEED + HELDOUT_SEED_OFFSET by default); with it, the held-out meshes exactly as
    `synthetic.load_heldout_meshes` draws them (seed EVAL_SEED by default)."""
    from gd_completion.synth.dataset import V2_SAMPLING, build_dataset
    from gd_completion.synth.meshio import HELDOUT_MESHES

    from .synthetic import EVAL_SEED

    if seed is None:
        seed = EVAL_SEED + HELDOUT_SEED_OFFSET if mesh_dir is None else EVAL_SEED
    if seed < EVAL_SEED:
        raise ValueError(f"held-out seed {seed}: below EVAL_SEED {EVAL_SEED} (training seeds)")
    if mesh_dir is None:
        data = build_dataset(n_samples, seed, options=V2_SAMPLING)
        meshes: list[str] = []
        name, where = "synthetic shapes", f"build_dataset({n_samples}, seed={seed}, V2 sampling, procedural)"
    else:
        data = build_dataset(n_samples, seed, meshes_dir=mesh_dir, mesh_fraction=1.0, only_meshes=HELDOUT_MESHES)
        meshes = mesh_names(mesh_dir, heldout=True)
        name, where = "held-out meshes", f"build_dataset({n_samples}, seed={seed}, the held-out meshes)"
    labels = sample_classes(data["kind"], meshes)
    return LabelledSet(name, where, list(np.asarray(data["partial"], np.float32)),
                       np.asarray(data["size"], np.float64).reshape(-1, 3),
                       list(np.asarray(data["complete"], np.float32)), [CLASSES[i] for i in labels], _one_hot(labels))


def pandaset_set(root: str | Path, *, preprocessing: Preprocessing | None = None, sensors: Sequence[int] = (0, 1),
                 max_per_vehicle: int = MAX_OBSERVATIONS, max_vehicles: int | None = None,
                 n_aggregate: int = AGGREGATE_POINTS) -> LabelledSet:
    """PandaSet's stationary vehicles with a label of PANDASET_CLASSES seen in two frames or more: up to
    `max_per_vehicle` evenly spaced observations (frame, sensor) of MIN_INPUT_POINTS points or more each; the
    upper bound is the vehicle's multi-frame aggregate, `n_aggregate` voxel-uniform points
    (`pandaset_eval.reference_sample`)."""
    from gd_completion.datasets.pandaset import PandaSetSequence

    from .pandaset_eval import MIN_INPUT_POINTS, collect_tracks, reference_sample, stationary_vehicles

    sequence = PandaSetSequence(root)
    vehicles = {u: label for u, label in stationary_vehicles(sequence, tuple(sensors)).items()
                if pandaset_classes(label)}
    if max_vehicles is not None:
        vehicles = dict(list(vehicles.items())[:max_vehicles])
    prep = replace(preprocessing or Preprocessing(), min_points=1)
    tracks = collect_tracks(sequence, vehicles, prep, sensors=tuple(sensors))
    partials, asides, sizes, complete, truth, accepted = [], [], [], [], [], []
    n_vehicles = 0
    for track in tracks.values():
        picks = track.input_frames(MIN_INPUT_POINTS, max_per_vehicle)
        if not picks or len(set(track.frames)) < 2:
            continue
        n_vehicles += 1
        aggregate = reference_sample(track.aggregate(), n_aggregate, seed=track.instance_id)
        row = np.isin(CLASSES, pandaset_classes(track.label))
        for k in picks:
            partials.append(np.asarray(track.points[k], np.float32))
            asides.append(track.asides[k])
            sizes.append(track.boxes[k].size)
            complete.append(aggregate)
            truth.append(track.label)
            accepted.append(row)
    where = (f"{Path(root).name}: {n_vehicles} stationary vehicles, <= {max_per_vehicle} "
             f"observations each (>= {MIN_INPUT_POINTS} points, sensors {', '.join(map(str, sensors))})")
    return LabelledSet("PandaSet 002", where,
                       partials, np.array(sizes, np.float64).reshape(-1, 3), complete, truth,
                       np.array(accepted, bool).reshape(-1, len(CLASSES)),
                       f"multi-frame aggregate, {n_aggregate} points", asides)


@dataclass
class SetResult:
    """Predictions of every input of INPUT_NAMES of one LabelledSet by each of C classifiers: `predicted[input]`
    (C, S) class indices, `correct[input]` (C, S) bool; `truth` the label per observation."""

    name: str
    source: str
    upper_bound: str
    truth: list[str]
    predicted: dict[str, np.ndarray]
    correct: dict[str, np.ndarray]
    seconds: float = 0.0

    @property
    def n(self) -> int:
        return len(self.truth)

    def counts(self) -> dict[str, int]:
        """Observations per truth label, most frequent first."""
        return dict(Counter(self.truth).most_common())

    def accuracies(self, name: str) -> np.ndarray:
        """(C,) fraction of observations whose prediction from input `name` is counted right, per classifier (NaN
        for none)."""
        correct = self.correct[name]
        return correct.mean(1) if self.n else np.full(len(correct), np.nan)

    def accuracy(self, name: str) -> float:
        """Mean over the classifiers of `accuracies` (NaN for no observation)."""
        return float(np.mean(self.accuracies(name))) if self.n else float("nan")

    def per_class(self, name: str) -> dict[str, float]:
        """Accuracy of input `name` per truth label (mean over the classifiers)."""
        truth = np.array(self.truth)
        return {label: float(self.correct[name][:, truth == label].mean()) for label in self.counts()}


def evaluate_set(classifiers: Sequence[PointNetClassifier], model: GGDNet, labelled: LabelledSet, *,
                 max_batch: int = 32, seed: int = 0) -> SetResult:
    """Classify every input of INPUT_NAMES of `labelled` with each of `classifiers`: the partials, their mirror +
    template prior (`priors.prior_outputs`), GGD-Net's completion and published output
    (`baselines.published_outputs`, computed once) and the upper-bound clouds."""
    t0 = time.perf_counter()
    if not labelled.partials:
        empty = {n: np.zeros((len(classifiers), 0), np.int64) for n in INPUT_NAMES}
        return SetResult(labelled.name, labelled.source, labelled.upper_bound, [], empty,
                         {n: np.zeros((len(classifiers), 0), bool) for n in INPUT_NAMES})
    nets = published_outputs(model, labelled.partials, labelled.sizes, max_batch=max_batch, asides=labelled.asides)
    measured = labelled.partials if labelled.asides is None else \
        [with_aside(p, b) for p, b in zip(labelled.partials, labelled.asides)]
    clouds: dict[str, Sequence[np.ndarray] | np.ndarray] = {
        "input": measured,
        "mirror_template": [prior_outputs(p, s)["mirror_template"] for p, s in zip(measured, labelled.sizes)],
        "ggd": nets.completion, "ggd_merge": nets.published, "complete": labelled.complete}
    rows = np.arange(len(labelled.partials))
    predicted = {name: np.stack([classify(c, clouds[name], seed=seed) for c in classifiers]) for name in INPUT_NAMES}
    correct = {name: labelled.accepted[rows, p] for name, p in predicted.items()}
    return SetResult(labelled.name, labelled.source, labelled.upper_bound, list(labelled.truth), predicted, correct,
                     time.perf_counter() - t0)


@dataclass
class ClassificationResult:
    """The experiment: each classifier's training and its accuracy on the validation shapes, and the predictions
    on each evaluated set."""

    train: list[ClassifierLog]
    validation: list[float]
    sets: list[SetResult]
    seconds: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def evaluate_classification(model: GGDNet, *, mesh_dir: str | Path | None = None, pandaset: str | Path | None = None,
                            preprocessing: Preprocessing | None = None, train_samples: int = 3000,
                            synthetic_samples: int = 330, mesh_samples: int = 128, sensors: Sequence[int] = (0, 1),
                            max_vehicles: int | None = None, max_per_vehicle: int = MAX_OBSERVATIONS,
                            settings: ClassifierSettings = ClassifierSettings(), seed: int = TRAIN_SEED,
                            classifiers: int = CLASSIFIERS, validation_samples: int | None = None,
                            max_batch: int = 32) -> ClassificationResult:
    """Train `classifiers` classifiers (seeds `seed`, `seed` + 1, ...) on the same `train_samples` complete shapes
    (drawn with `seed`, the training meshes of `mesh_dir` when given), check each on `validation_samples` complete
    shapes drawn alike (VALIDATION_SEED; default a sixth of `train_samples`), and classify every input on the
    procedural held-out set (`synthetic_samples`), the held-out meshes (`mesh_samples`, needs `mesh_dir`) and
    PandaSet (`pandaset`, a sequence folder); a count of 0 or a missing folder skips a set (noted)."""
    if classifiers < 1 or (validation_samples is not None and validation_samples < 1):
        raise ValueError(f"classifiers={classifiers} and validation_samples={validation_samples} must be >= 1")
    if seed == VALIDATION_SEED:   # build_dataset seeds each shape by (seed, index)
        raise ValueError(f"training seed {seed}: its shapes would be the validation shapes (seed {VALIDATION_SEED})")
    seconds: dict[str, float] = {}
    notes: list[str] = []
    t0 = time.perf_counter()
    meshes = Path(mesh_dir) if mesh_dir is not None and Path(mesh_dir).is_dir() else None
    if mesh_dir is not None and meshes is None:
        notes.append(f"mesh folder {mesh_dir} not found: trained on procedural shapes only, held-out meshes skipped")
    shapes, labels, where = training_shapes(train_samples, seed=seed, mesh_dir=meshes)
    n_checks = max(2, train_samples // 6) if validation_samples is None else validation_samples
    checks, check_labels, _ = training_shapes(n_checks, seed=VALIDATION_SEED, mesh_dir=meshes)
    seconds["training data"] = time.perf_counter() - t0
    trained = [train_classifier(shapes, labels, settings=settings, seed=seed + i, source=where)
               for i in range(classifiers)]
    nets = [net for net, _ in trained]
    seconds["training"] = sum(log.seconds for _, log in trained)
    validation = [float(np.mean(classify(net, checks) == check_labels)) for net in nets]
    sets: list[SetResult] = []
    plans: list[tuple[str, Callable[[], LabelledSet]]] = []
    if synthetic_samples > 0:
        plans.append(("synthetic shapes", lambda: synthetic_set(synthetic_samples)))
    if mesh_samples > 0 and meshes is not None:
        plans.append(("held-out meshes", lambda: synthetic_set(mesh_samples, mesh_dir=meshes)))
    if pandaset is not None and (Path(pandaset) / "lidar").is_dir():
        root = Path(pandaset)
        plans.append(("PandaSet", lambda: pandaset_set(root, preprocessing=preprocessing, sensors=sensors,
                                                       max_per_vehicle=max_per_vehicle, max_vehicles=max_vehicles)))
    elif pandaset is not None:
        notes.append(f"PandaSet folder {pandaset} not found: skipped")
    for name, build in plans:
        t1 = time.perf_counter()
        sets.append(evaluate_set(nets, model, build(), max_batch=max_batch))
        seconds[name] = time.perf_counter() - t1
    return ClassificationResult([log for _, log in trained], validation, sets, seconds, notes)


def _cell(values: np.ndarray, signed: bool = False) -> str:
    """A table cell of per-classifier values: their mean, with their range when there are several ("-" for none);
    `signed` (differences) shows the signs and "to" between the range's ends."""
    if not len(values) or np.isnan(values).all():
        return "-"
    form, between = ("{:+.3f}", " to ") if signed else ("{:.3f}", "-")
    mean = form.format(float(np.mean(values)))
    if len(values) < 2:
        return mean
    return f"{mean} ({form.format(float(np.min(values)))}{between}{form.format(float(np.max(values)))})"


def _difference(s: SetResult, a: str, b: str) -> str:
    """Accuracy of input `a` minus input `b` (`_cell` of the per-classifier differences)."""
    return _cell(s.accuracies(a) - s.accuracies(b), signed=True)


def _summary(result: ClassificationResult) -> str:
    """The comparison asked for: completions vs raw inputs, and complete shapes vs completions, on the held-out
    meshes (the procedural set when the meshes were skipped); means over the classifiers, ranges per classifier."""
    chosen = next((s for s in result.sets if s.name == "held-out meshes"), None) or \
        next((s for s in result.sets if s.name == "synthetic shapes"), None)
    if chosen is None or chosen.n == 0:
        return "No synthetic set was classified: no completion-vs-input comparison."
    return (f"On the {chosen.name} (n = {chosen.n}): GGD-Net published - raw input = "
            f"{_difference(chosen, 'ggd_merge', 'input')} (network output - raw input "
            f"{_difference(chosen, 'ggd', 'input')}; mirror + template - raw input "
            f"{_difference(chosen, 'mirror_template', 'input')}); complete shapes - GGD-Net published = "
            f"{_difference(chosen, 'complete', 'ggd_merge')} (complete - network output "
            f"{_difference(chosen, 'complete', 'ggd')}).")


def classification_section(result: ClassificationResult) -> str:
    """Markdown: accuracy of every input on every set (mean over the classifiers and their range), the comparison
    line, per-class accuracy per set and the classifiers' training and validation."""
    logs, sets = result.train, result.sets
    parts = ["## Completion for classification (downstream)"]
    if logs:
        log = logs[0]
        seeds = ", ".join(str(g.seed) for g in logs)
        parts.append(
            f"{len(logs)} PointNet{'s' if len(logs) > 1 else ''} (shared MLP 3-64-128-256, max pool, "
            f"256-128-{len(CLASSES)}; seeds {seeds}) trained on complete shapes only (the same {log.n_shapes} "
            f"shapes of {log.source}; {log.settings.epochs} epochs, {log.settings.n_points} random points per shape "
            f"and step, jitter, per-axis scale and y-mirror augmentation; "
            f"{sum(g.seconds for g in logs) / len(logs):.0f} s each) classify each input in the normalised box frame "
            f"(vehicle length 1; the box size itself is not an input). Classes: {', '.join(CLASSES)}. Last epoch on "
            f"their training batches: loss " + " / ".join(f"{g.loss:.3f}" for g in logs) + ", accuracy "
            + " / ".join(f"{g.accuracy:.3f}" for g in logs) + "; accuracy on complete shapes drawn like the training "
            f"ones (seed {VALIDATION_SEED}): " + " / ".join(f"{v:.3f}" for v in result.validation) + ".")
    if sets:
        several = len(logs) > 1
        headers = ["input"] + [f"{s.name} (n = {s.n})" for s in sets]
        rows = [[INPUT_TITLES[n]] + [_cell(s.accuracies(n)) for s in sets] for n in INPUT_NAMES]
        parts.append(("Accuracy (mean over the classifiers, their range in brackets):" if several else "Accuracy:")
                     + "\n\n" + markdown_table(headers, rows))
        parts.append(_summary(result) + " The mirror + template prior's template is a sedan fitted to the box: it "
                     "favours the car class. On PandaSet the last row classifies the multi-frame aggregate (every "
                     "frame's points, registration and label noise included), not a true complete shape.")
        parts.append("Sets: " + "; ".join(
            f"{s.name}: {s.source}; upper bound: {s.upper_bound}; classes "
            + ", ".join(f"{k} {v}" for k, v in s.counts().items()) for s in sets) + ".")
        for s in sets:
            counts = s.counts()
            table = markdown_table(["input"] + [f"{k} ({v})" for k, v in counts.items()],
                                   [[INPUT_TITLES[n]] + list(s.per_class(n).values()) for n in INPUT_NAMES])
            truth = np.tile(np.array(s.truth), s.predicted["ggd_merge"].shape[0])
            predicted, correct = s.predicted["ggd_merge"].ravel(), s.correct["ggd_merge"].ravel()
            confusions = []
            for label in counts:
                wrong = Counter(CLASSES[p] for p, ok in zip(predicted[truth == label], correct[truth == label])
                                if not ok)
                if wrong:
                    confusions.append(f"{label} -> " + ", ".join(f"{c} {k}" for c, k in wrong.most_common(3)))
            parts.append(f"### Per-class accuracy: {s.name}\n\n{table}\n\nMisclassified (GGD-Net published"
                         + (f", all {s.predicted['ggd_merge'].shape[0]} classifiers" if several else "") + "): "
                         + ("; ".join(confusions) if confusions else "none") + ".")
    else:
        parts.append("No set was classified.")
    if result.notes:
        parts.append("Notes: " + "; ".join(result.notes) + ".")
    return "\n\n".join(parts)
