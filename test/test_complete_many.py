"""`complete` over many bags: inputs, resuming, bad bags among good ones, and the Ray engine against the local one."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gd_completion.bags.batch import BagJob, complete_many, expand_inputs, plan_jobs, ray_resources
from gd_completion.cli import main
from gd_completion.errors import BagError
from gd_completion.settings import CompletionSettings

KITTI = "kitti-object-sample/training"
NAMES = ("a", "b", "c")  # three bags of two KITTI frames each


@pytest.fixture(scope="module")
def model_path() -> str:
    from gd_completion.model.checkpoint import DEFAULT_WEIGHTS

    if not DEFAULT_WEIGHTS.is_file():
        pytest.skip("shipped weights absent")
    return str(DEFAULT_WEIGHTS)


@pytest.fixture(scope="module")
def small_bags(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Folder with bags a, b, c: KITTI frames 0-1, 2-3 and 4-5, converted with `gd-completion convert kitti`."""
    root = tmp_path_factory.mktemp("many")
    (root / "bags").mkdir()
    for k, name in enumerate(NAMES):
        split = root / "kitti" / name / "training"
        for sub, suffix in (("calib", ".txt"), ("label_2", ".txt"), ("velodyne", ".bin")):
            (split / sub).mkdir(parents=True)
            for frame in (2 * k, 2 * k + 1):
                os.symlink(shared_data / KITTI / sub / f"{frame:06d}{suffix}", split / sub / f"{frame:06d}{suffix}")
        assert main(["convert", "kitti", str(split), str(root / "bags" / name), "--quiet"]) == 0
    return root / "bags"


@pytest.fixture(scope="module")
def local_outputs(small_bags: Path, model_path: str) -> Path:
    """The three bags completed by `--engine local`, the reference for everything else."""
    out = small_bags.parent / "local"
    args = ["complete", str(small_bags / "*"), str(out), "--model", model_path, "--threads", "1", "--quiet"]
    assert main(args) == 0
    return out


def _files(bag: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(bag.iterdir())}


def _corrupt(src: Path, dst: Path) -> None:
    """A copy of bag `src` whose MCAP file is cut in half."""
    dst.mkdir()
    for f in src.iterdir():
        data = f.read_bytes()
        (dst / f.name).write_bytes(data[: len(data) // 2] if f.suffix == ".mcap" else data)


def test_inputs_globs_and_manifests(small_bags: Path, tmp_path: Path) -> None:
    manifest = tmp_path / "bags.txt"
    manifest.write_text(f"# three bags\n{small_bags / 'c'}\n\n{small_bags / 'a'}  # first\n")
    assert expand_inputs([str(manifest), str(small_bags / "*")]) == [small_bags / n for n in ("c", "a", "b")]
    assert [j.out for j in plan_jobs([str(small_bags / "a"), "x/b.mcap"], tmp_path)] == [tmp_path / "a",
                                                                                         tmp_path / "b"]
    with pytest.raises(BagError, match="would both write"):
        plan_jobs([str(small_bags / "a"), "other/a"], tmp_path)
    with pytest.raises(BagError, match="no bag matches"):
        expand_inputs([str(tmp_path / "none*")])


def test_ray_resources() -> None:
    assert ray_resources("cpu", 1) == {"num_cpus": 1, "num_gpus": 0}
    assert ray_resources("cuda:1", 2) == {"num_cpus": 2, "num_gpus": 1}


@pytest.mark.integration
def test_local_many_matches_single_bag(small_bags: Path, local_outputs: Path, model_path: str, tmp_path: Path,
                                       capsys: pytest.CaptureFixture) -> None:
    assert sorted(p.name for p in local_outputs.iterdir()) == list(NAMES)  # no temporaries left
    single = tmp_path / "b"  # the bag's name is in its files: compare bags of one name
    assert main(["complete", str(small_bags / "b"), str(single), "--model", model_path, "--threads", "1",
                 "--quiet"]) == 0
    assert _files(single) == _files(local_outputs / "b")


@pytest.mark.integration
def test_local_resumes_and_reports_bad_bags(small_bags: Path, local_outputs: Path, model_path: str, tmp_path: Path,
                                           capsys: pytest.CaptureFixture) -> None:
    _corrupt(small_bags / "a", tmp_path / "broken")
    out = tmp_path / "out"
    out.mkdir()
    shutil.copytree(local_outputs / "a", out / "a")  # finished before the run was killed
    (out / ".b.x1y2.partial").mkdir()  # a killed writer's temporary
    manifest = tmp_path / "bags.txt"
    manifest.write_text("\n".join(str(p) for p in (small_bags / "a", tmp_path / "broken", small_bags / "b",
                                                   small_bags / "c")))
    code = main(["complete", str(manifest), str(out), "--model", model_path, "--threads", "1", "--quiet"])
    captured = capsys.readouterr()
    assert code == 2
    assert f"skipped {small_bags / 'a'} -> {out / 'a'}: output exists" in captured.out
    assert "4 bags: 2 completed, 1 skipped (output exists), 1 failed" in captured.out
    assert f"failed {tmp_path / 'broken'} -> {out / 'broken'}: {tmp_path / 'broken'}: " in captured.err
    assert sorted(p.name for p in out.iterdir()) == ["a", "b", "c"]
    for name in NAMES:
        assert _files(out / name) == _files(local_outputs / name)


@pytest.mark.integration
def test_killed_run_resumes_with_the_remaining_bags(small_bags: Path, local_outputs: Path, model_path: str,
                                                   tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A real kill: SIGKILL once the first output bag is there, then the same command again."""
    out = tmp_path / "out"
    args = ["complete", str(small_bags / "*"), str(out), "--model", model_path, "--threads", "1", "--quiet"]
    proc = subprocess.Popen([sys.executable, "-m", "gd_completion.cli", *args], cwd=Path(__file__).parents[1],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        end = time.monotonic() + 120.0
        while not (out / "a").exists() and proc.poll() is None and time.monotonic() < end:
            time.sleep(0.01)
    finally:
        proc.kill()
        proc.wait()
    finished = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
    assert "a" in finished and len(finished) < len(NAMES), finished     # killed mid-way
    assert main(args) == 0
    printed = capsys.readouterr().out
    for name in NAMES:
        verb = "skipped" if name in finished else "done"
        assert f"{verb} {small_bags / name} -> {out / name}" in printed, printed
        assert _files(out / name) == _files(local_outputs / name)
    assert sorted(p.name for p in out.iterdir()) == list(NAMES)      # no partial temporaries left


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray of 2 CPUs for the module; `complete_many` uses a Ray already started and leaves it up."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING")
    yield ray
    ray.shutdown()


@pytest.mark.integration
def test_ray_matches_local(local_ray, small_bags: Path, local_outputs: Path, model_path: str,
                           tmp_path: Path) -> None:
    jobs = plan_jobs([str(small_bags / "*")], tmp_path / "ray")
    outcomes = complete_many(jobs, CompletionSettings.offline(model_path=model_path, num_threads=1), engine="ray",
                             workers=2, progress=False)
    assert [o.status for o in outcomes] == ["done"] * 3, [o.detail for o in outcomes]
    assert sum(o.frames for o in outcomes) == 6
    for name in NAMES:  # every file byte for byte: messages, metadata and provenance (the engine is not recorded)
        assert _files(tmp_path / "ray" / name) == _files(local_outputs / name)


@pytest.mark.integration
def test_ray_resumes_and_reports_bad_bags(local_ray, small_bags: Path, local_outputs: Path, model_path: str,
                                          tmp_path: Path) -> None:
    _corrupt(small_bags / "b", tmp_path / "broken")
    out = tmp_path / "out"
    out.mkdir()
    shutil.copytree(local_outputs / "c", out / "c")
    os.utime(out / "c", (1, 1))
    (out / ".a.abcd.partial").mkdir()
    jobs = [BagJob(small_bags / n, out / n) for n in NAMES] + [BagJob(tmp_path / "broken", out / "broken")]
    seen: list[str] = []
    outcomes = complete_many(jobs, CompletionSettings.offline(model_path=model_path, num_threads=1), engine="ray",
                             workers=2, progress=False, report=lambda o: seen.append(o.job.name))
    assert [o.status for o in outcomes] == ["done", "done", "skipped", "failed"]
    assert sorted(seen) == ["a", "b", "broken"]  # c was not processed again
    assert outcomes[3].detail.startswith(f"{tmp_path / 'broken'}: ") and "cannot open bag" in outcomes[3].detail
    assert (out / "c").stat().st_mtime == 1
    assert sorted(p.name for p in out.iterdir()) == list(NAMES)
    for name in NAMES:
        assert _files(out / name) == _files(local_outputs / name)


@pytest.mark.integration
def test_ray_cli_single_bag_and_exit_code(local_ray, small_bags: Path, local_outputs: Path, model_path: str,
                                          tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "a"
    assert main(["complete", str(small_bags / "a"), str(out), "--engine", "ray", "--workers", "2",
                 "--model", model_path, "--quiet"]) == 0
    assert _files(out) == _files(local_outputs / "a")
    assert "1 bags: 1 completed" in capsys.readouterr().out
    assert main(["complete", str(small_bags / "a"), str(out), "--engine", "ray", "--quiet"]) == 2
    assert "output exists" in capsys.readouterr().err
