"""POCO training, the ``poco`` refiner and ``datagen poco eval`` (CPU, one torch thread).

Smoke setup: a pool of 6 samples (3 built-ins capsule, torus, box_with_hole, each at a random size
in [0.05, 0.15] m and rotation, 2 cases of 1-3 views each), the ``tiny`` preset, batch 4, Adam
lr 3e-3, 100 steps, seed 0 (~40 s on one idle core; fewer steps stay at the majority class). Then,
on those same training samples (all their queries), the mean IoU over both classes at the best
threshold of a grid must beat predicting the majority class by >= 0.1, and the mean loss of the
last 10 steps must be below that of the first 10.

Test-time fine-tuning must really change the prediction (a copy's weights move, and one step of the
shipped weights lowers the loss of its own targets) and never the shared, cached model.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from typer.testing import CliRunner  # noqa: E402

from datagen.errors import ConfigError  # noqa: E402
from datagen.pipeline.imaging import Observation  # noqa: E402
from datagen.pipeline.keys import key_centres, unpack_keys  # noqa: E402
from datagen.pipeline.objects.spec import BUILTIN_PREFIX  # noqa: E402
from datagen.pipeline.refine.base import RefineRequest, band_keys  # noqa: E402
from datagen.pipeline.refine.freespace import sensor_empty  # noqa: E402
from datagen.pipeline.refine.poco.inputs import observation_inputs, predict_probs, query_keys  # noqa: E402
from datagen.pipeline.refine.poco.network import PocoModel  # noqa: E402
from datagen.pipeline.refine.poco.refiner import PocoRefiner  # noqa: E402
from datagen.training.poco_checkpoints import export_weights  # noqa: E402
from datagen.training.poco_samples import generate_pool, load_pool, save_pool, sized_spec  # noqa: E402
from datagen.training.poco_train import TrainOptions, train  # noqa: E402
from datagen.training.poco_validation import evaluate_pool, threshold_metrics  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402

SHAPES = [(n, BUILTIN_PREFIX + n, None) for n in ("capsule", "torus", "box_with_hole")]


@pytest.fixture(autouse=True)
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def pool_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("poco_pool")
    pool = generate_pool(SHAPES, tasks=3, samples_per_task=2, seed=0)
    save_pool(pool, out / "pool.npz")
    return out


def options(out: Path, **kwargs) -> TrainOptions:
    base = dict(out=out, preset="tiny", seed=0, batch=4, lr=3e-3, synth=0, val_fraction=0.0, checkpoint_every=1000)
    base.update(kwargs)
    return TrainOptions(**base)


def test_pool_roundtrip_and_contents(pool_dir: Path) -> None:
    pool = load_pool(pool_dir / "pool.npz")
    assert len(pool) == 6
    for sample in pool:
        assert sample.inputs.shape == sample.directions.shape and sample.inputs.shape[1] == 3
        np.testing.assert_allclose(np.linalg.norm(sample.directions, axis=1), 1.0, atol=1e-5)
        assert sample.queries.shape[0] == sample.labels.size == sample.is_gt.size == sample.is_box.size
        assert 0 < sample.labels.mean() < 1
        assert not sample.is_gt[sample.is_box].any()


def test_smoke_training_learns(pool_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (out / "pool.npz").write_bytes((pool_dir / "pool.npz").read_bytes())
    result = train(options(out, steps=100), log=lambda line: None)
    losses = result["losses"]
    assert len(losses) == 100
    assert np.mean(losses[-10:]) < np.mean(losses[:10])

    model = PocoModel("tiny")
    payload = torch.load(out / "last.pt", weights_only=True)
    model.load_state_dict(payload["state_dict"])
    pool = load_pool(out / "pool.npz")
    ev = evaluate_pool(model, pool, seed=0, device=torch.device("cpu"))
    majority = ev["label"].mean() >= 0.5
    baseline = threshold_metrics(ev["prob"], ev["label"], ev["is_gt"], -1.0 if majority else 2.0)["miou"]
    best = max(threshold_metrics(ev["prob"], ev["label"], ev["is_gt"], t)["miou"] for t in np.linspace(0.05, 0.95, 19))
    assert best >= baseline + 0.1, (best, baseline)


def test_resume_continues_from_saved_step(pool_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (out / "pool.npz").write_bytes((pool_dir / "pool.npz").read_bytes())
    first = train(options(out, steps=3, checkpoint_every=3), log=lambda line: None)
    assert first["step"] == 3
    assert torch.load(out / "last.pt", weights_only=True)["step"] == 3
    lines: list[str] = []
    second = train(options(out, steps=5, checkpoint_every=5, resume=True), log=lines.append)
    assert any("resumed at step 3" in line for line in lines)
    assert second["step"] == 5 and len(second["losses"]) == 2
    assert torch.load(out / "last.pt", weights_only=True)["step"] == 5
    # Without --resume an existing run is never overwritten.
    with pytest.raises(ConfigError, match="already holds a training run"):
        train(options(out, steps=7), log=lambda line: None)
    assert torch.load(out / "last.pt", weights_only=True)["step"] == 5


def test_init_starts_from_weights_with_a_new_optimiser(pool_dir: Path, tmp_path: Path) -> None:
    first, second = tmp_path / "first", tmp_path / "second"
    for folder in (first, second):
        folder.mkdir()
        (folder / "pool.npz").write_bytes((pool_dir / "pool.npz").read_bytes())
    train(options(first, steps=2, checkpoint_every=2), log=lambda line: None)
    weights = tmp_path / "w.pt"
    export_weights(first / "last.pt", weights)
    lines: list[str] = []
    result = train(options(second, steps=4, checkpoint_every=4, init=weights), log=lines.append)
    assert any("initialised from" in line and "step 2" in line for line in lines)
    assert result["step"] == 4 and len(result["losses"]) == 2
    with pytest.raises(ConfigError, match="not found"):
        train(options(tmp_path / "third", steps=4, init=tmp_path / "absent.pt"), log=lambda line: None)


@pytest.fixture(scope="module")
def request_and_config():
    from datagen.pipeline.objects.prepare import prepare_object
    from datagen.pipeline.scanning import scan_task
    from datagen.pipeline.viewspace import build_view_space

    config = GenerationConfig(refiner="poco")
    spec = sized_spec("capsule", BUILTIN_PREFIX + "capsule", None, 0.08)
    prepared = prepare_object(spec, config)
    imaging = scan_task(prepared, 1, config, build_view_space(config.view_space))
    observation = Observation.combine([imaging.observations[3], imaging.observations[9]])
    return RefineRequest(observation, 7, spec.object_id, 1), config


def test_refiner_contract_and_determinism(request_and_config) -> None:
    request, config = request_and_config
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = PocoModel("tiny_sv").eval()
    refiner = PocoRefiner(config, model, "test", 0.5)
    _queries, prob = refiner.probabilities(request)
    refiner.threshold = float(np.median(prob))  # random weights: cut at the median so R is non-trivial
    first = refiner.refine([request])[0]
    second = refiner.refine([request, request])
    assert first.size > 0
    np.testing.assert_array_equal(first, second[0])
    np.testing.assert_array_equal(first, second[1])
    observation = request.observation
    band = band_keys(observation.keys, config.band_keys_sq)
    assert np.isin(first, band).all()
    assert not np.isin(first, observation.keys).any()
    assert not sensor_empty(first, observation, config.camera, config.voxel_size, config.grid_offset).any()
    assert np.all(np.diff(first) > 0)
    other = PocoRefiner(config, model, "test", refiner.threshold).refine([request])[0]
    np.testing.assert_array_equal(first, other)


def test_refiner_finetune_runs(request_and_config) -> None:
    request, config = request_and_config
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = PocoModel("tiny_sv").eval()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    refiner = PocoRefiner(config, model, "test", 0.5, finetune_steps=1)
    a = refiner.refine([request])[0]
    b = refiner.refine([request])[0]
    np.testing.assert_array_equal(a, b)
    for key, value in model.state_dict().items():  # the shared model is never changed
        assert torch.equal(value, before[key])

    # Fine-tuning changes the prediction: the same queries get other probabilities than without it...
    plain_queries, plain = PocoRefiner(config, model, "test", 0.5).probabilities(request)
    tuned_queries, tuned = refiner.probabilities(request)
    np.testing.assert_array_equal(plain_queries, tuned_queries)
    assert not np.allclose(plain, tuned, atol=1e-4)
    # ...because a copy's weights moved (not merely other random draws): with identical draws, the copy
    # predicts otherwise, and the shared model is still untouched.
    observation = request.observation
    inputs, directions = observation_inputs(observation, config.voxel_size, config.grid_offset)
    draws = np.random.default_rng(0), torch.Generator().manual_seed(0)
    tuned_model = refiner._finetuned(request, inputs, directions, *draws)
    assert tuned_model is not model and not tuned_model.training
    moved = [not torch.equal(p, q) for p, q in zip(model.parameters(), tuned_model.parameters(), strict=True)]
    assert sum(moved) > len(moved) // 2
    centres = key_centres(unpack_keys(plain_queries), config.voxel_size, config.grid_offset)

    def probs(net: PocoModel) -> np.ndarray:
        rng, generator = np.random.default_rng(5), torch.Generator().manual_seed(5)
        return predict_probs(net, inputs, directions, centres, rng, generator, torch.device("cpu"))

    assert not np.allclose(probs(model), probs(tuned_model), atol=1e-4)
    for key, value in model.state_dict().items():
        assert torch.equal(value, before[key])


def test_finetune_fits_the_observation(request_and_config) -> None:
    """One fine-tuning step of the shipped weights lowers the loss of its own targets (AIR's rule):
    the observed key centres inside, the sensor-empty band keys outside."""
    from datagen.pipeline.refine.poco.checkpoint import load_checkpoint
    from datagen.pipeline.refine.poco.refiner import BUILTIN_WEIGHTS

    if not BUILTIN_WEIGHTS.is_file():
        pytest.skip("no shipped weights")
    request, config = request_and_config
    model = load_checkpoint(BUILTIN_WEIGHTS)
    observation = request.observation
    inputs, directions = observation_inputs(observation, config.voxel_size, config.grid_offset)
    unknown, _, empty = query_keys(observation, config)
    outside = key_centres(unpack_keys(unknown[empty]), config.voxel_size, config.grid_offset)
    assert outside.shape[0] > 0

    def target_loss(net: PocoModel) -> float:
        def probs(points: np.ndarray) -> np.ndarray:
            rng, generator = np.random.default_rng(5), torch.Generator().manual_seed(5)
            return predict_probs(net, inputs, directions, points, rng, generator, torch.device("cpu"))

        inside_p, outside_p = probs(inputs), probs(outside)
        return float(-np.log(np.clip(inside_p, 1e-6, 1)).mean() - np.log(np.clip(1 - outside_p, 1e-6, 1)).mean())

    refiner = PocoRefiner(config, model, "test", config.poco_threshold, finetune_steps=1)
    tuned = refiner._finetuned(request, inputs, directions, np.random.default_rng(1), torch.Generator().manual_seed(1))
    base_loss, tuned_loss = target_loss(model), target_loss(tuned)
    assert tuned_loss < 0.9 * base_loss, (base_loss, tuned_loss)
    # And the refiner's R(O) with fine-tuning differs from R(O) without it, within the same queries.
    plain = PocoRefiner(config, model, "test", config.poco_threshold).refine([request])[0]
    fine = refiner.refine([request])[0]
    queries = query_keys(observation, config)[1]
    assert np.isin(fine, queries).all()
    assert not np.array_equal(plain, fine)


def test_config_poco_fields(tmp_path: Path) -> None:
    weights = tmp_path / "w.pt"
    weights.write_bytes(b"abc")
    a = GenerationConfig(refiner="poco", poco_weights=str(weights))
    moved = tmp_path / "x.pt"
    moved.write_bytes(b"abc")
    assert a.config_hash() == GenerationConfig(refiner="poco", poco_weights=str(moved)).config_hash()
    moved.write_bytes(b"abd")
    assert a.config_hash() != GenerationConfig(refiner="poco", poco_weights=str(moved)).config_hash()
    assert GenerationConfig().config_hash() != GenerationConfig(poco_threshold=0.3).config_hash()


def test_eval_command_prints_table(tmp_path: Path, monkeypatch) -> None:
    from datagen.cli import common
    from datagen.cli.main import poco_app

    monkeypatch.setattr(common.console, "_width", 400)  # no wrapped cells
    from datagen.pipeline.refine.poco.checkpoint import save_checkpoint

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = PocoModel("tiny_sv")
    weights = tmp_path / "tiny.pt"
    save_checkpoint(model, weights)
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule size=0.06\n")
    args = ["eval", "--objects", str(objects), "--weights", str(weights), "--views", "0"]
    result = CliRunner().invoke(poco_app, args)
    assert result.exit_code == 0, result.output
    for word in ("capsule", "poco", "carve", "oracle", "mean", "prec.", "hidden"):
        assert word in result.output
    assert "poisson" not in result.output
    pytest.importorskip("open3d")
    with_poisson = CliRunner().invoke(poco_app, [*args, "--poisson"])
    assert with_poisson.exit_code == 0, with_poisson.output
    rows = [line for line in with_poisson.output.splitlines() if "poisson" in line]
    assert len(rows) == 2  # the capsule's row and the mean row


def test_factory_loads_shipped_weights_once() -> None:
    from datagen.pipeline.refine.factory import make_refiner
    from datagen.pipeline.refine.poco.refiner import BUILTIN_WEIGHTS

    if not BUILTIN_WEIGHTS.is_file():
        pytest.skip("no shipped weights")
    config = GenerationConfig(refiner="poco")
    first, second = make_refiner(config), make_refiner(config)
    assert first.name == "poco" and len(first.weights_id) == 64
    assert first.model is second.model  # type: ignore[attr-defined]
    assert first.threshold == config.poco_threshold  # type: ignore[attr-defined]
