"""studies/labels/authors_trainers.py's pieces on a made-up training script: the launcher's overrides and
probe, the stand-in PC-NBV loader, and the sha256 check. The authors' trainers themselves run by hand
(studies/labels/results/authors-trainers.md); nothing here needs their repository."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest
from support.benchmarks import REPO_ROOT, load_study

STANDINS = REPO_ROOT / "studies" / "labels" / "authors_standins"

TRAIN = """
import sys
import config
epochs = 1000
import torch
from torch.utils.data import DataLoader, TensorDataset
loader = DataLoader(TensorDataset(torch.arange(10.0).reshape(5, 2), torch.ones(5)), batch_size=2)
w = torch.zeros(2, requires_grad=True)
for e in range(epochs):
    for x, y in loader:
        ((x @ w - y) ** 2).mean().backward()
print("epochs", epochs, "path", config.PATH, "args", sys.argv[1:])
"""


@pytest.fixture(scope="module")
def driver() -> ModuleType:
    return load_study("labels.authors_trainers")


def test_the_launcher_overrides_without_editing_and_probes_what_was_read(tmp_path: Path) -> None:
    pytest.importorskip("torch")
    (tmp_path / "train.py").write_text(TRAIN)
    (tmp_path / "config.py").write_text('PATH = "theirs"\n')
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    probe = tmp_path / "probe.json"
    command = [sys.executable, str(STANDINS / "launch.py"), "--script", str(tmp_path / "train.py")]
    command += ["--set-module", 'config.PATH="ours"', "--set-global", "epochs=2", "--probe", str(probe), "--", "-x"]
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "epochs 2 path ours args ['-x']" in done.stdout
    found = json.loads(probe.read_text())
    assert found["exit"] == 0 and found["error"] is None and found["cuda_extensions_imported"] == []
    (loader,) = found["loaders"]
    assert (loader["dataset"], loader["dataset_len"], loader["passes"], loader["batches"]) == ("TensorDataset", 5, 2, 6)
    assert loader["samples"] == 10
    assert loader["first_batch"] == [{"shape": [2, 2], "dtype": "float32"}, {"shape": [2], "dtype": "float32"}]
    assert len(found["losses"]) == 6 and found["losses"][0] == pytest.approx(1.0)  # mean of (0 - 1)^2 at w = 0
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.name in before} == before


def test_a_failing_script_reports_its_error_and_exit(tmp_path: Path) -> None:
    (tmp_path / "train.py").write_text("raise RuntimeError('their bug')\n")
    probe = tmp_path / "probe.json"
    command = [
        sys.executable,
        str(STANDINS / "launch.py"),
        "--script",
        str(tmp_path / "train.py"),
        "--probe",
        str(probe),
    ]
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and "their bug" in done.stderr
    assert json.loads(probe.read_text())["error"] == "RuntimeError: their bug"


def test_the_pcnbv_standin_serves_row_i_of_four_saved_tensors(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    tensors = [torch.rand(3, 4, 3), torch.rand(3, 5, 3), torch.rand(3, 32), torch.rand(3, 32)]
    paths = [tmp_path / f"{i}.pt" for i in range(4)]
    for tensor, path in zip(tensors, paths, strict=True):
        torch.save(tensor, path)
    spec = importlib.util.spec_from_file_location("standin_dataset", STANDINS / "pcnbv" / "dataset" / "dataset.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    dataset = module.ShapeNet3(*(str(p) for p in paths))
    assert len(dataset) == 3
    for got, tensor in zip(dataset[2], tensors, strict=True):
        assert torch.equal(got, tensor[2])
    with pytest.raises(NotImplementedError, match=r"train\.py uses ShapeNet3"):
        module.ShapeNet("a", "b")


def test_sha256s_see_an_edit_and_skip_links(driver: ModuleType, tmp_path: Path) -> None:
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "link.npy").symlink_to(tmp_path / "a.py")
    first = driver.sha256s(tmp_path)
    assert set(first) == {"a.py"}
    (tmp_path / "a.py").write_text("x = 2\n")
    assert driver.sha256s(tmp_path)["a.py"] != first["a.py"]
    assert set(driver.TRAINERS) >= {"nbv-net-master", "ma_scvp", "sc-net", "PC-NBV_pytorch"}
    assert {t.layout for t in driver.TRAINERS.values()} == {"mascvp", "nbvnet", "pcnbv"}


def test_the_harness_takes_its_paths_from_arguments_and_deletes_nothing(
    driver: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """No path of one machine by default, a --work folder that holds anything refused (never emptied),
    and an existing report written over only with --replace (issue 42)."""
    with pytest.raises(SystemExit):
        driver.main([])
    missing = capsys.readouterr().err
    assert "--authors" in missing and "--work" in missing
    used = tmp_path / "used"
    used.mkdir()
    (used / "keep.txt").write_text("mine\n")
    with pytest.raises(SystemExit):
        driver.main(["--authors", str(tmp_path), "--work", str(used)])
    assert "is not a new or empty folder" in capsys.readouterr().err
    assert (used / "keep.txt").read_text() == "mine\n"
    committed = tmp_path / "result.md"
    committed.write_text("committed\n")
    with pytest.raises(SystemExit):
        driver.main(["--authors", str(tmp_path), "--work", str(tmp_path / "new"), "--out", str(committed)])
    assert "exists; give another --out, or --replace" in capsys.readouterr().err
    assert committed.read_text() == "committed\n"
    with pytest.raises(SystemExit, match="no Networks_pytorch folder"):  # past the paths: the clone is checked
        driver.main(["--authors", str(tmp_path), "--work", str(tmp_path / "new"), "--out", str(committed), "--replace"])
