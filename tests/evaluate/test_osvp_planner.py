"""`datagen evaluate --planner osvp:FILE`: a checkpoint trained by the osvp package plans through the
`ViewScorer` interface, from the same input a shard holds, and bad checkpoints are one error line."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from support.storage import build_dataset, config
from typer.testing import CliRunner

from datagen.cli.main import app
from datagen.evaluate.episode import run_episode
from datagen.evaluate.planners import make_planner
from datagen.evaluate.scene import build_scene
from datagen.evaluate.scored import CHOICE_THRESHOLD
from datagen.evaluate.situation import RefinedScene, Situation
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.refine.factory import make_refiner
from datagen.pipeline.viewspace import build_view_space
from schemas.errors import DatagenError

pytestmark = pytest.mark.skipif(importlib.util.find_spec("osvp") is None, reason="the osvp package is not installed")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from osvp.train import TrainOptions, train

    folder = tmp_path_factory.mktemp("osvp-planner")
    build_dataset(str(folder / "data"), finalise_index=True)
    train(TrainOptions(data=str(folder / "data"), out=folder / "run", epochs=1, batch_size=32))
    return folder / "run" / "best.pt"


def capsule_situation(folder: Path) -> Situation:
    """The capsule at rotation 0 from initial view 3, under the tests' config (refiner none)."""
    objects = folder / "objects.txt"
    objects.write_text("builtin:capsule\n")
    cfg = config()
    prepared = prepare_object(read_objects_file(objects).objects[0], cfg)
    scene = build_scene(prepared, 0, cfg, build_view_space(cfg.view_space))
    return Situation(RefinedScene(scene, make_refiner(cfg), cfg), 3)


def test_a_trained_checkpoint_plans_the_views_its_decodings_choose(checkpoint: Path, tmp_path: Path) -> None:
    """`osvp+threshold:FILE` takes the views scored above one half (the paper's rule); plain `osvp:FILE`
    takes what the checkpoint's default decoding selects from the same probabilities."""
    situation = capsule_situation(tmp_path)
    planner = make_planner(f"osvp+threshold:{checkpoint}")
    assert planner.name == f"osvp+threshold:{checkpoint}" and planner.uses_refinement
    plan = planner.plan(situation)
    assert plan.probabilities is not None and plan.probabilities.shape == (32,)
    expected = tuple(int(v) for v in np.flatnonzero(plan.probabilities > CHOICE_THRESHOLD) if v != 3)
    assert plan.views == expected
    default = make_planner(f"osvp:{checkpoint}")
    again = default.plan(situation)
    assert np.array_equal(again.probabilities, plan.probabilities)
    state = np.zeros(32, dtype=np.float32)
    state[3] = 1.0
    chosen = default.scorer.select_views(again.probabilities, state, None)  # type: ignore[attr-defined]
    assert again.views == tuple(int(v) for v in np.flatnonzero(chosen))
    episode = run_episode(planner, situation)
    assert episode.visited[0] == 3 and episode.planner == planner.name and episode.refiner == "none"


def test_a_damaged_checkpoint_is_a_named_error(tmp_path: Path) -> None:
    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"\x00" * 64)
    with pytest.raises(DatagenError, match="not a readable osvp checkpoint"):
        make_planner(f"osvp:{broken}")
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    result = CliRunner().invoke(app, ["evaluate", "--objects", str(objects), "-p", f"osvp:{broken}"])
    assert result.exit_code == 2
    assert [line for line in result.stderr.splitlines() if line] == [
        line for line in result.stderr.splitlines() if line.startswith("error:") and "broken.pt" in line
    ]


def test_a_gain_checkpoint_is_played_step_by_step(tmp_path: Path) -> None:
    """A checkpoint trained on every view's gain (``--target gain``) is a next-best-view planner:
    `datagen evaluate` asks it after every view and visits its largest predicted gain."""
    from osvp.planning import NextViewCheckpointScorer, load_scorer
    from osvp.train import TrainOptions, train

    from datagen.evaluate.sequential import DEFAULT_TOTAL_VIEWS, SequentialPlanner
    from schemas.planning import NextViewObservation, NextViewScorer

    build_dataset(str(tmp_path / "data"), finalise_index=True)
    outcome = train(
        TrainOptions(
            data=str(tmp_path / "data"), out=tmp_path / "run", epochs=1, batch_size=32, target="gain", source="observed"
        )
    )
    assert outcome.best_metric == "best_view_accuracy" and 0.0 <= outcome.best_score <= 1.0
    assert 0.0 <= outcome.history[0]["gain_mae"] <= 1.0
    path = tmp_path / "run" / "best.pt"
    scorer = load_scorer(path)
    assert isinstance(scorer, NextViewCheckpointScorer) and isinstance(scorer, NextViewScorer)
    situation = capsule_situation(tmp_path)
    scene = situation.scene
    planner = make_planner(f"osvp:{path}")
    assert isinstance(planner, SequentialPlanner) and not planner.uses_refinement
    plan = planner.plan(situation)
    assert plan.ordered and len(plan.views) == DEFAULT_TOTAL_VIEWS - 1 and 3 not in plan.views
    # the first visit is the largest predicted gain for what the initial view saw
    state = np.zeros(32, dtype=np.float32)
    state[3] = 1.0
    first = NextViewObservation(views=(3,), view_state=state, cloud=scene.observed_points([3]), grid=None)
    scores = scorer.next_view_scores(first)
    assert scores.shape == (32,) and ((scores >= 0) & (scores <= 1)).all()
    assert plan.views[0] == int(np.argmax(np.where(state == 0, scores, -np.inf)))
    episode = run_episode(planner, situation)
    assert len(episode.visited) == DEFAULT_TOTAL_VIEWS and episode.refiner == "-"


def test_the_gain_target_needs_a_version_3_dataset(tmp_path: Path) -> None:
    from osvp.data import DataError
    from osvp.train import TrainOptions, train

    build_dataset(str(tmp_path / "v2"), finalise_index=True, schema_version=2)
    with pytest.raises(
        DataError,
        match=r"target 'gain' needs every case's next-view labels and occupancy grid, which a version-2 dataset lacks",
    ):
        train(TrainOptions(data=str(tmp_path / "v2"), out=tmp_path / "run", epochs=1, target="gain"))
    assert not (tmp_path / "run").exists()


def test_grid_checkpoints_see_the_grid_the_generator_stores(tmp_path: Path) -> None:
    """An NBVNet-style checkpoint is played step by step and an SCVP-style one plans one shot, both
    from the occupancy grid evaluate builds; for the initial view it is exactly the grid the dataset
    stores for that single-view case of the same object and rotation (independent code paths: the
    generator's shard against evaluate's own walk of the scene)."""
    from osvp.planning import CheckpointScorer, NextViewCheckpointScorer
    from osvp.train import TrainOptions, train

    import storage
    from datagen.evaluate.sequential import SequentialPlanner

    data = str(tmp_path / "data")
    build_dataset(data, finalise_index=True)
    dataset = storage.open_dataset(data)
    index = dataset.index.to_pydict()
    row = next(
        i
        for i, (name, state) in enumerate(zip(index["object_name"], index["view_state"], strict=True))
        if name == "capsule" and int(state) == 1 << 3
    )
    stored = dataset.next_view(row, grid=True).grid
    assert stored is not None and stored.shape == (32, 32, 32)
    seen: list[np.ndarray] = []

    for network in ("nbvnet", "scvp"):
        train(TrainOptions(data=data, out=tmp_path / network, epochs=1, batch_size=32, network=network))
        planner = make_planner(f"osvp:{tmp_path / network / 'best.pt'}")
        scorer = planner.scorer_for(None) if isinstance(planner, SequentialPlanner) else planner.scorer  # type: ignore[attr-defined, arg-type]
        assert isinstance(scorer, NextViewCheckpointScorer if network == "nbvnet" else CheckpointScorer)
        assert scorer.uses_grid and not planner.uses_refinement
        asked = scorer.predict if network == "nbvnet" else scorer  # type: ignore[attr-defined]
        answer = asked.view_probabilities

        def spy(points, view_state, grid=None, answer=answer):  # type: ignore[no-untyped-def]
            seen.append(np.array(grid))
            return answer(points, view_state, grid)

        asked.view_probabilities = spy
        plan = planner.plan(capsule_situation(tmp_path))
        assert np.array_equal(seen[0], stored), network
        first = answer(None, np.eye(32, dtype=np.float32)[3], stored)
        best = int(np.argmax(np.where(np.arange(32) != 3, first, -np.inf)))
        if network == "nbvnet":
            assert plan.ordered and len(plan.views) == 9 and plan.views[0] == best and len(seen) == 9
        else:
            assert len(seen) == 1 and np.array_equal(plan.probabilities, first)
        seen.clear()
