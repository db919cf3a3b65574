"""The floor: the best fixed view sets of a training dataset (`datagen.evaluate.fixed`), against a brute-force
search over every view subset, played by `datagen evaluate` and as every planner's lift at equal views."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from support import storage as fx
from typer.testing import CliRunner

from datagen.cli.main import app
from datagen.errors import PlannerError
from datagen.evaluate.fixed import case_weights, choose_fixed_plans, spread_views
from datagen.evaluate.planners import make_planner
from datagen.evaluate.protocol import PlannerContext
from datagen.pipeline.coverage import view_masks


@pytest.fixture(scope="module")
def training(tmp_path_factory: pytest.TempPathFactory) -> str:
    """Capsule and cone at rotation 0 (refiner none): 64 single-view cases."""
    url = str(tmp_path_factory.mktemp("fixed") / "train")
    fx.build_dataset(url, finalise_index=True)
    return url


def brute_force_plans(size: int, without: int | None = None) -> tuple[tuple[int, ...], float]:
    """The size-subset of views (not ``without``) with the highest mean coverage over every single-view case
    of the training tasks (each case: its view plus the subset, over all keys some view sees)."""
    tasks = [view_masks(result.sets.visible)[1] for result in fx.task_results()]
    views = [v for v in range(32) if v != without]
    best: tuple[float, tuple[int, ...]] = (-1.0, ())
    for subset in itertools.combinations(views, size):
        chosen = np.uint64(sum(1 << v for v in subset))
        total = 0.0
        for masks in tasks:
            by_subset = (masks & chosen) != 0
            for initial in range(32):
                seen = by_subset | ((masks >> np.uint64(initial)) & np.uint64(1)).astype(bool)
                total += np.count_nonzero(seen) / masks.size
        mean = total / (32 * len(tasks))
        if mean > best[0] + 1e-12:  # combinations come in lexicographic order: the first best stays
            best = (mean, subset)
    return best[1], best[0]


def test_fixed_plans_equal_a_brute_force_search(training: str) -> None:
    weights = case_weights(training)
    assert (weights.tasks, weights.cases) == (2, 64)
    plans = choose_fixed_plans(weights, training, initial_views=(0, 5, 20), sizes=range(1, 4))
    for size in (1, 2, 3):
        views, mean = brute_force_plans(size)
        assert plans.by_size[size].views == views and plans.by_size[size].exact
        assert plans.by_size[size].mean_coverage == pytest.approx(mean, abs=1e-9)
        for initial in (0, 5, 20):
            played = plans.plan(size, initial)
            assert initial not in played.views and len(played.views) == size
            if initial in views:
                assert played.views == brute_force_plans(size, without=initial)[0]
            else:
                assert played == plans.by_size[size]
    assert any(line.startswith("  1 view:") for line in plans.summary())
    assert "exact for sizes 1-3" in plans.summary()[0]


def test_spread_takes_the_farthest_view_each_time() -> None:
    positions = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0], [10.0, 0.0, 0.0], [6.0, 0.0, 0.0]])
    assert spread_views(positions, 0, 4) == (3, 4, 2, 1)
    assert spread_views(positions, 3, 2) == (0, 4)
    assert spread_views(positions, 0, 9) == (3, 4, 2, 1)  # never more than the other views


def test_fixed_without_a_dataset_is_one_error_naming_the_option(tmp_path: Path) -> None:
    with pytest.raises(PlannerError, match="give --fixed-from URL"):
        make_planner("fixed:match=oracle", PlannerContext())
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    result = CliRunner().invoke(app, ["evaluate", "--objects", str(objects), "-p", "oracle", "-p", "fixed"])
    assert result.exit_code == 2
    assert result.output.splitlines() == [
        "error: planner 'fixed' plays the best fixed view sets of a training dataset: give --fixed-from URL"
    ]
    missing = tmp_path / "no-dataset"
    result = CliRunner().invoke(
        app, ["evaluate", "--objects", str(objects), "-p", "fixed", "--fixed-from", str(missing)]
    )
    assert result.exit_code == 2 and len(result.output.splitlines()) == 1
    assert result.output.startswith("error: ") and str(missing) in result.output


def test_every_planner_is_judged_against_the_fixed_plan_at_equal_views(training: str, tmp_path: Path) -> None:
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:cone\n")
    config = tmp_path / "config.toml"
    config.write_text('refiner = "none"\n')
    args = ["evaluate", "--workers", "1", "--objects", str(objects), "--config", str(config)]
    args += ["--initial-views", "0,9", "--fixed-from", training, "--tau", "0.9", "--json"]
    args += ["-p", "oracle", "-p", "fixed:match=oracle", "-p", "oracle:budget=1", "-p", "fixed:2", "-p", "spread:2"]
    args += ["-p", "spread:match=oracle"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["fixed"]["tasks"] == 2 and report["fixed"]["plans"]["1"]["exact"]
    runs = {(r["planner"], r["initial_view"]): r for r in report["runs"]}
    for view in (0, 9):
        oracle, fixed = runs["oracle", view], runs["fixed:match=oracle", view]
        assert len(fixed["planned"]) == len(oracle["planned"]) and view not in fixed["planned"]
        assert oracle["matched_fixed_coverage"] == fixed["coverage"]
        assert oracle["lift_fixed"] == pytest.approx(oracle["coverage"] - fixed["coverage"], abs=1e-5)
        spread = runs["spread:match=oracle", view]
        assert oracle["matched_spread_coverage"] == spread["coverage"] and oracle["lift_spread"] is not None
        best = runs["oracle:budget=1", view]
        assert len(best["planned"]) == 1 and best["lift_fixed"] >= -1e-9  # the best single view beats any constant
        assert fixed["lift_fixed"] is None and fixed["count_curve"] is not None
        # fixed:2 is the initial view and one more: its coverage is the curve at one new view
        assert runs["fixed:2", view]["count_curve"][1] == pytest.approx(runs["fixed:2", view]["coverage"] / 100)
    rows = {row["planner"]: row for row in report["rows"]}
    assert rows["fixed:2"]["views_to_tau"] is not None and rows["oracle"]["views_to_tau"] is None
    assert rows["oracle"]["lift_fixed"] is not None and rows["spread:2"]["lift_fixed"] is None


@pytest.mark.parametrize(
    ("spec", "objective", "refines"),
    [
        ("oracle", "cover", True),
        ("oracle:alpha=5", "cover", True),
        ("oracle:budget=2", "max_coverage", False),
        ("oracle:tau=0.9", "partial_cover", False),
        ("oracle:objective=partial_cover,tau=0.8", "partial_cover", False),
    ],
)
def test_an_oracle_labels_under_the_settings_it_names(spec: str, objective: str, refines: bool) -> None:
    planner = make_planner(spec, PlannerContext())
    assert planner.name == spec and planner.uses_refinement is refines
    assert planner.config.label_objective == objective  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("oracle:depth=3", "give label settings as objective=V, alpha=V, budget=V, tau=V"),
        ("oracle:budget=two", "budget=two is not a whole number"),
        ("oracle:tau=1.5", "oracle setting tau: Input should be less than or equal to 1"),
        ("oracle:objective=best", "oracle setting objective: unknown label objective 'best'; choose one of cover"),
    ],
)
def test_a_bad_oracle_setting_is_one_planner_error(spec: str, message: str) -> None:
    with pytest.raises(PlannerError) as info:
        make_planner(spec, PlannerContext())
    assert message in str(info.value) and "\n" not in str(info.value)


def test_a_hundred_thousand_tasks_keep_the_search_within_int64() -> None:
    """A whole case weighs `SCALE` up to 4,096 tasks of 32 views (their plans unchanged) and less past
    that, so that every case's weight, and the search's sums of gains on top, fit in int64: weights made
    as 100,000 tasks' would give (their total at the headroom) choose a plan of every size."""
    from datagen.evaluate.fixed import SCALE, SEARCH_HEADROOM, CaseWeights, case_scale

    assert case_scale(4096, 32) == SCALE and case_scale(1, 32) == SCALE
    scale = case_scale(100_000, 32)
    assert scale < SCALE and 100_000 * 32 * scale <= SEARCH_HEADROOM
    rng = np.random.default_rng(3)
    masks = np.unique(rng.integers(1, 1 << 32, size=400, dtype=np.uint64))
    shares = rng.random(masks.size)
    weights = (shares / shares.sum() * (SEARCH_HEADROOM - 1)).astype(np.int64)
    found = CaseWeights(masks, weights, 0, tasks=100_000, cases=100_000 * 32, num_views=32, scale=scale)
    plans = choose_fixed_plans(found, "made up", sizes=range(1, 6), node_budget=20_000)
    assert sorted(plans.by_size) == [1, 2, 3, 4, 5]
    assert all(len(plan.views) == size and plan.mean_coverage > 0 for size, plan in plans.by_size.items())


def test_fixed_plans_are_kept_per_dataset_and_chosen_again_when_the_tasks_change(
    training: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The cache (`datagen.evaluate.fixed_cache`) gives back exactly the plans chosen; another set of
    initial views or a dataset with other committed tasks is another key; a damaged file is chosen again."""
    import shutil

    from datagen.evaluate import fixed_cache

    chosen = []
    real = fixed_cache.choose_fixed_plans

    def counting(*args: object, **kwargs: object):  # type: ignore[no-untyped-def]
        chosen.append(1)
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(fixed_cache, "choose_fixed_plans", counting)
    cache = tmp_path / "cache"
    first, remembered = fixed_cache.cached_fixed_plans(training, (0, 8), cache)
    again, remembered_again = fixed_cache.cached_fixed_plans(training, (0, 8), cache)
    assert (remembered, remembered_again, len(chosen)) == (False, True, 1)
    assert again.to_record() == first.to_record() and again.without == first.without
    fixed_cache.cached_fixed_plans(training, (0, 9), cache)
    assert len(chosen) == 2
    other = tmp_path / "other"
    shutil.copytree(training, other)
    assert fixed_cache.dataset_key(str(other), (0, 8)) == fixed_cache.dataset_key(training, (0, 8))
    fx.build_dataset(str(tmp_path / "more"), attempt_id="another-attempt", finalise_index=True)
    assert fixed_cache.dataset_key(str(tmp_path / "more"), (0, 8)) != fixed_cache.dataset_key(training, (0, 8))
    for path in cache.iterdir():
        path.write_text("{not json")
    repaired, remembered = fixed_cache.cached_fixed_plans(training, (0, 8), cache)
    assert not remembered and repaired.to_record() == first.to_record() and len(chosen) == 3
