"""``datagen shards digest``: the content digest that says two datasets hold the same samples, pinned on
the engine's shared dataset so that a change to what the pipeline writes (a refactor that should not
change it, a new dependency) fails here rather than in a user's reproduction.

The pinned value was made by the code of issue 51's storage re-layering, whose `real-val-none` digest
(192 real tasks) equals the one made before it: the re-layering changed no stored byte.
(Re-pinned once since, when the digest stopped reading every sample a second time.)
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from support import storage as fx
from support.shards import EngineDataset, engine_dataset  # noqa: F401 (the fixture)
from typer.testing import CliRunner

from datagen.cli.main import app
from schemas.shard import LABEL_COLUMN, MASKS
from storage import committed_tasks, dataset_digest, open_location

PINNED = "c168f60d63169b35bd0fa83c9c9b14e17142801f62c8c78c6345c22abe438933"
"""The digest of capsule, cone and torus at 2 rotations, refiner none (`support.shards`)."""

runner = CliRunner()


def test_the_engine_dataset_digest_is_pinned_and_the_same_in_any_store(engine_dataset: EngineDataset) -> None:  # noqa: F811
    result = runner.invoke(app, ["shards", "digest", engine_dataset.url, engine_dataset.memory_url])
    assert result.exit_code == 0, result.output
    lines = [line.split() for line in result.output.splitlines()]
    assert [line[3] for line in lines] == [engine_dataset.url, engine_dataset.memory_url]
    samples = dataset_digest(engine_dataset.url).samples
    assert [line[:3] for line in lines] == [[PINNED, str(samples), str(samples)]] * 2


def test_one_label_bit_changes_the_digest(engine_dataset: EngineDataset, tmp_path: Path) -> None:  # noqa: F811
    copy = Path(shutil.copytree(engine_dataset.url, tmp_path / "ds"))
    record = committed_tasks(open_location(str(copy)))[0]
    with fx.shard_group(copy / record.shard, mode="r+") as group:
        masks = np.asarray(group[MASKS][...])
        masks[0, LABEL_COLUMN] ^= np.uint64(1)
        group[MASKS][...] = masks
    assert dataset_digest(str(copy)).sha256 != PINNED


def test_a_missing_dataset_is_one_error_line_and_the_others_are_digested(
    engine_dataset: EngineDataset,  # noqa: F811
    tmp_path: Path,
) -> None:
    result = runner.invoke(app, ["shards", "digest", str(tmp_path), engine_dataset.url])
    assert result.exit_code == 2 and result.output.count("error:") == 1, result.output
    assert f"{PINNED}  " in result.output and result.output.rstrip().endswith(engine_dataset.url)
