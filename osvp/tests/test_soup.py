"""``osvp soup``: the soup's every weight is the mean of its ingredients' (checked tensor by tensor
against the two files), it plays like any checkpoint, it records what it is made of, and checkpoints
of different networks or targets are refused in one line."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from osvp.checkpoint import CheckpointError, load_checkpoint
from osvp.cli import main
from osvp.planning import load_scorer
from osvp.train import TrainOptions, file_sha256, train

from storage.samples import GRID_SIDE


@pytest.fixture(scope="module")
def runs(dataset_url: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two seeds of one grid network and one of another target, one epoch each."""
    folder = tmp_path_factory.mktemp("soup")
    made = {}
    for name, seed, target in (("a", 1, "mincover"), ("b", 2, "mincover"), ("other-target", 1, "near_best")):
        out = folder / name
        options = TrainOptions(data=dataset_url, out=out, epochs=1, batch_size=16, network="scvp", seed=seed)
        train(replace(options, target=target))
        made[name] = out / "last.pt"
    return made


def test_the_soup_is_the_mean_of_its_ingredients_and_plays(
    runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "soup.pt"
    assert main(["soup", str(runs["a"]), str(runs["b"]), "--out", str(out)]) == 0
    assert file_sha256(out) in capsys.readouterr().out
    a, b, soup = (load_checkpoint(path) for path in (runs["a"], runs["b"], out))
    averaged = 0
    for name, tensor in soup.data["model"].items():
        left, right = a.data["model"][name], b.data["model"][name]
        if tensor.is_floating_point():
            assert torch.allclose(tensor, (left + right) / 2, atol=1e-6), name
            averaged += not torch.equal(left, right)
        else:
            assert torch.equal(tensor, left), name
    assert averaged > 0  # two seeds: the ingredients differ, so the check above could fail
    assert [part["sha256"] for part in soup.data["soup"]] == [file_sha256(runs["a"]), file_sha256(runs["b"])]
    assert "optimiser" not in soup.data and soup.target == a.target
    scorer = load_scorer(out)
    grid = np.zeros((GRID_SIDE,) * 3, dtype=np.float32)
    state = np.zeros(a.num_views, dtype=np.float32)
    state[0] = 1.0
    probabilities = scorer.view_probabilities(np.zeros((8, 3), dtype=np.float32), state, grid)  # type: ignore[union-attr]
    assert probabilities.shape == (a.num_views,) and np.all((probabilities >= 0) & (probabilities <= 1))


def test_a_soup_of_different_targets_or_of_one_file_is_one_line(
    runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(CheckpointError, match="its target differs"):
        from osvp.soup import make_soup

        make_soup([runs["a"], runs["other-target"]], tmp_path / "bad.pt")
    assert main(["soup", str(runs["a"]), "--out", str(tmp_path / "one.pt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "two or more checkpoints" in err[0]
    assert not (tmp_path / "bad.pt").exists() and not (tmp_path / "one.pt").exists()
