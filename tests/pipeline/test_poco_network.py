"""POCO network (datagen/pipeline/refine/poco): official layout and counts, checkpoints, exact decoder rewrite,
order invariance over neighbours, quantized sampling and kNN tables, and a cheap forward pass."""

from __future__ import annotations

import copy
import os
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from torch import nn

from datagen.pipeline.refine.poco import (
    PRESETS,
    PocoModel,
    PocoPreset,
    get_preset,
    knn,
    load_checkpoint,
    quantized_sampling,
    save_checkpoint,
    spatial_tables,
)
from datagen.pipeline.refine.poco.checkpoint import infer_preset
from datagen.pipeline.refine.poco.network import FKAConv, InterpAttentionKHeadsNet, gather_neighbours
from datagen.pipeline.refine.poco.spatial import CONV_TABLES, KnnBackend, level_points, level_sizes, pykdtree_available

torch.set_num_threads(1)


def sphere_points(n: int, seed: int, batch: int = 1, radius: float = 0.4) -> torch.Tensor:
    """(B, 3, n) points on a noisy sphere, the scale POCO's weights expect (unit box)."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(batch, 3, n, generator=g)
    pts = pts / pts.norm(dim=1, keepdim=True) * radius
    return pts + 0.005 * torch.randn(batch, 3, n, generator=g)


def box_queries(m: int, seed: int, batch: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(batch, 3, m, generator=g) - 0.5


def randomise_(model: nn.Module, seed: int) -> None:
    """Perturb every parameter and BN buffer so no term is trivially zero, one or symmetric."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, tensor in model.state_dict().items():
            if not tensor.is_floating_point() or name.endswith("norm_radius"):
                continue
            if name.endswith("running_var"):
                tensor.copy_(0.5 + torch.rand(tensor.shape, generator=g))
            else:
                tensor.add_(0.1 * torch.randn(tensor.shape, generator=g))


@pytest.fixture(scope="module")
def official() -> PocoModel:
    return PocoModel("official").eval()


# --------------------------------------------------------------------------------------------------
# Layout and counts of the official network


EXPECTED_SHAPES = {
    "net.cv0.norm_radius": (1,),
    "net.cv0.alpha": (1,),
    "net.cv0.beta": (1,),
    "net.cv0.cv.weight": (64, 3, 1, 16),
    "net.cv0.fc1.weight": (16, 3, 1, 1),
    "net.cv0.fc2.weight": (16, 32, 1, 1),
    "net.cv0.fc3.weight": (16, 32, 1, 1),
    "net.cv0.bn1.weight": (16,),
    "net.cv0.bn2.bias": (16,),
    "net.bn0.running_mean": (64,),
    "net.bn0.num_batches_tracked": (),
    "net.resnetb01.cv0.weight": (32, 64, 1),
    "net.resnetb01.cv0.bias": (32,),
    "net.resnetb01.bn0.running_var": (32,),
    "net.resnetb01.cv1.cv.weight": (32, 32, 1, 16),
    "net.resnetb01.cv1.norm_radius": (1,),
    "net.resnetb01.bn1.weight": (32,),
    "net.resnetb01.cv2.weight": (64, 32, 1),
    "net.resnetb01.bn2.bias": (64,),
    "net.resnetb10.cv2.weight": (128, 32, 1),
    "net.resnetb10.shortcut.weight": (128, 64, 1),
    "net.resnetb10.bn_shortcut.running_mean": (128,),
    "net.resnetb41.cv1.cv.weight": (512, 512, 1, 16),
    "net.resnetb41.cv2.weight": (1024, 512, 1),
    "net.cv5.weight": (1024, 2048, 1),
    "net.bn5.running_var": (1024,),
    "net.cv3d.weight": (512, 1536, 1),
    "net.cv2d.weight": (256, 768, 1),
    "net.cv1d.weight": (128, 384, 1),
    "net.cv0d.weight": (64, 192, 1),
    "net.fcout.weight": (32, 64, 1),
    "net.fcout.bias": (32,),
    "projection.fc1.weight": (32, 35, 1, 1),
    "projection.fc2.weight": (32, 32, 1, 1),
    "projection.fc3.weight": (32, 32, 1, 1),
    "projection.fc_query.weight": (64, 32, 1, 1),
    "projection.fc_value.weight": (32, 32, 1, 1),
    "projection.fc8.weight": (2, 32, 1),
    "projection.fc8.bias": (2,),
}


def test_official_counts(official: PocoModel) -> None:
    state = official.state_dict()
    assert official.count_parameters() == 12_790_454
    assert len(state) == 363
    assert sum(t.numel() for t in state.values()) == 12_812_133
    assert [name for name, _ in official.named_children()] == ["net", "projection"]
    assert sum(p.numel() for p in official.net.parameters() if p.requires_grad) == 12_783_956
    assert sum(p.numel() for p in official.projection.parameters()) == 6_498
    dead = sum(p.numel() for p in (*official.net.cv5.parameters(), *official.net.bn5.parameters()))
    assert dead == 2_100_224
    radii = [name for name, p in official.named_parameters() if name.endswith("norm_radius")]
    assert len(radii) == 10
    assert not any(p.requires_grad for name, p in official.named_parameters() if name.endswith("norm_radius"))


def test_official_names_and_shapes(official: PocoModel) -> None:
    state = official.state_dict()
    for name, shape in EXPECTED_SHAPES.items():
        assert tuple(state[name].shape) == shape, name
    backbone = [name for name, _ in official.net.named_children()]
    assert backbone[:22] == [
        "cv0", "bn0", "resnetb01", "resnetb10", "resnetb11", "resnetb20", "resnetb21", "resnetb30",
        "resnetb31", "resnetb40", "resnetb41", "cv5", "bn5", "cv3d", "bn3d", "cv2d", "bn2d", "cv1d",
        "bn1d", "cv0d", "bn0d", "fcout",
    ]  # fmt: skip
    assert {name for name, _ in official.projection.named_children()} == {
        "fc1", "fc2", "fc3", "fc8", "fc_query", "fc_value"
    }  # fmt: skip
    block = official.net.resnetb10
    assert {name for name, _ in block.named_children()} == {
        "cv0", "bn0", "cv1", "bn1", "cv2", "bn2", "shortcut", "bn_shortcut"
    }  # fmt: skip
    assert isinstance(block.cv1, FKAConv)
    assert isinstance(block.cv0, nn.Conv1d) and isinstance(official.projection.fc1, nn.Conv2d)
    assert isinstance(official.projection.fc8, nn.Conv1d)
    assert {name for name, _ in official.net.cv0.named_parameters(recurse=False)} == {"norm_radius", "alpha", "beta"}
    assert isinstance(official.net.cv0.bn1, nn.InstanceNorm2d)
    # Same-width blocks have no shortcut parameters.
    assert not any(k.startswith("net.resnetb01.shortcut") or k.startswith("net.resnetb01.bn_short") for k in state)


def test_preset_counts() -> None:
    # Cross-checks with the spec's table for other widths (hidden 32 / 16 with latent 32).
    assert PocoModel(PocoPreset("h32", hidden=32, latent=32, decoder_k=64, heads=64)).count_parameters() == 3_220_054
    assert PocoModel(PocoPreset("h16", hidden=16, latent=32, decoder_k=64, heads=64)).count_parameters() == 822_950
    assert PocoModel(PocoPreset("l64", hidden=64, latent=64, decoder_k=64, heads=64)).count_parameters() == 12_807_158
    counts = {}
    for name, preset in PRESETS.items():
        model = PocoModel(preset)
        counts[name] = model.count_parameters()
        assert tuple(model.state_dict()["net.cv0.cv.weight"].shape) == (preset.hidden, preset.input_channels, 1, 16)
        print(
            f"POCO preset {name}: {counts[name]:,} trainable parameters "
            f"(hidden {preset.hidden}, latent {preset.latent}, K {preset.decoder_k}, heads {preset.heads}, "
            f"{preset.input_channels} input channels, {preset.num_input_points} points)"
        )
    assert counts["official"] == 12_790_454
    # The _sv variants differ only by the first FKAConv's extra input channels.
    for base in ("official", "small", "tiny"):
        hidden = PRESETS[base].hidden
        assert counts[f"{base}_sv"] - counts[base] == 3 * hidden * 16
    assert counts["tiny"] < counts["small"] < counts["official"]
    # fast differs from small only in what is not a weight (K, input points): small's weights load into it
    assert counts["fast_sv"] == counts["small_sv"]
    fast = PocoModel(get_preset("fast_sv"))
    fast.load_state_dict(PocoModel(get_preset("small_sv")).state_dict(), strict=True)
    with pytest.raises(ValueError):
        get_preset("nope")
    with pytest.raises(ValueError):
        PocoPreset("bad", hidden=16, latent=16, decoder_k=16, heads=4, input_channels=4)


# --------------------------------------------------------------------------------------------------
# Checkpoints


def test_checkpoint_round_trip(tmp_path: Path, official: PocoModel) -> None:
    model = PocoModel("tiny")
    randomise_(model, 3)
    model.eval()
    pts = sphere_points(500, 0)
    queries = box_queries(300, 1)
    tables = model.tables(pts, 7, queries=queries)
    expected = model(pts, model.features(pts), tables, queries, tables["proj_indices"])

    # Our own format: {"state_dict", "preset", "epoch"}.
    save_checkpoint(model, tmp_path / "ours.pt", epoch=3)
    loaded = load_checkpoint(tmp_path / "ours.pt")
    assert loaded.preset == model.preset and not loaded.training
    assert torch.equal(loaded(pts, loaded.features(pts), tables, queries, tables["proj_indices"]), expected)

    # Bare state dict: the preset comes from the shapes.
    torch.save(model.state_dict(), tmp_path / "bare.pt")
    assert load_checkpoint(tmp_path / "bare.pt").preset == get_preset("tiny")

    # The release layout {"epoch", "state_dict", "optimizer"} loads with weights_only=True.
    # (An Adam state dict's shape, written by hand: building a real optimiser imports torch's compiler stack.)
    adam = {
        "state": {0: {"step": torch.tensor(5.0), "exp_avg": torch.zeros(3), "exp_avg_sq": torch.zeros(3)}},
        "param_groups": [{"lr": 1e-3, "betas": (0.9, 0.999), "eps": 1e-8, "weight_decay": 0, "params": [0]}],
    }
    torch.save({"epoch": 5, "state_dict": model.state_dict(), "optimizer": adam}, tmp_path / "release.pth")
    released = load_checkpoint(tmp_path / "release.pth")
    for name, tensor in model.state_dict().items():
        assert torch.equal(released.state_dict()[name], tensor), name

    # The official network itself, bare, is recognised by its shapes.
    torch.save(official.state_dict(), tmp_path / "official.pt")
    assert load_checkpoint(tmp_path / "official.pt").preset == get_preset("official")
    assert infer_preset(official.state_dict()).name == "official"

    # strict=True: a missing or an extra tensor is an error.
    state = model.state_dict()
    missing = {k: v for k, v in state.items() if k != "projection.fc8.bias"}
    torch.save({"state_dict": missing}, tmp_path / "missing.pt")
    with pytest.raises(RuntimeError, match="Missing"):
        load_checkpoint(tmp_path / "missing.pt", "tiny")
    torch.save({**state, "net.extra": torch.zeros(1)}, tmp_path / "extra.pt")
    with pytest.raises(RuntimeError, match="Unexpected"):
        load_checkpoint(tmp_path / "extra.pt", "tiny")
    # Non-tensor payloads are refused by weights_only loading or by the format check.
    torch.save({"state_dict": {"a": 1}}, tmp_path / "junk.pt")
    with pytest.raises(ValueError):
        load_checkpoint(tmp_path / "junk.pt")


# --------------------------------------------------------------------------------------------------
# Decoder: reference layout vs exact fast rewrite


@pytest.mark.parametrize(("latent", "k", "heads"), [(32, 64, 64), (16, 32, 8), (16, 16, 4)])
def test_fast_decoder_matches_reference(latent: int, k: int, heads: int) -> None:
    with torch.random.fork_rng(devices=[]):  # module init only; the data below uses its own generator
        torch.manual_seed(0)
        decoder = InterpAttentionKHeadsNet(latent, 2, k=k, heads=heads)
    randomise_(decoder, 1)
    g = torch.Generator().manual_seed(2)
    batch, n, m = 2, 400, 257
    latents = torch.randn(batch, latent, n, generator=g, requires_grad=True)
    pos = torch.rand(batch, 3, n, generator=g) - 0.5
    queries = torch.rand(batch, 3, m, generator=g) - 0.5
    index = torch.randint(0, n, (batch, m, k), generator=g)

    reference = decoder(latents, pos, queries, index, fast=False)
    (grad_ref,) = torch.autograd.grad(reference.square().sum(), latents)
    assert reference.shape == (batch, 2, m)
    for layout in ("first", "last"):  # both memory layouts of the fast path
        decoder.fast_layout = layout
        fast = decoder(latents, pos, queries, index, fast=True)
        assert fast.shape == (batch, 2, m)
        assert (reference - fast).abs().max().item() <= 1e-5
        # Gradients agree too (training uses the fast path).
        (grad_fast,) = torch.autograd.grad(fast.square().sum(), latents)
        assert torch.allclose(grad_ref, grad_fast, atol=1e-5, rtol=1e-4)


def test_decode_chunking_and_flag() -> None:
    model = PocoModel("small")
    randomise_(model, 4)
    model.eval()
    g = torch.Generator().manual_seed(5)
    latents = torch.randn(1, model.preset.latent, 600, generator=g)
    pts = torch.rand(1, 3, 600, generator=g) - 0.5
    queries = torch.rand(1, 3, 1000, generator=g) - 0.5
    index = model.query_knn(pts, queries)
    whole = model.decode(latents, pts, queries, index, chunk_size=1000)
    chunked = model.decode(latents, pts, queries, index, chunk_size=129)
    reference = model.decode(latents, pts, queries, index, fast=False, chunk_size=300)
    assert torch.allclose(whole, chunked, atol=1e-6)
    assert (whole - reference).abs().max().item() <= 1e-5
    model.fast_decoder = False
    assert torch.allclose(model.decode(latents, pts, queries, index), reference, atol=1e-6)
    assert model.decode(latents, pts, queries[:, :, :0], index[:, :0]).shape == (1, 2, 0)


# --------------------------------------------------------------------------------------------------
# Invariance to the order of neighbours


def permute_neighbours(tables: dict[str, torch.Tensor], seed: int) -> dict[str, torch.Tensor]:
    """Every table's K axis shuffled, independently per row."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for name, table in tables.items():
        if name.startswith("sample") or table.shape[2] == 1:
            out[name] = table
            continue
        order = torch.argsort(torch.rand(table.shape, generator=g), dim=2)
        out[name] = torch.gather(table, 2, order)
    return out


@pytest.mark.parametrize("training", [False, True])
def test_neighbour_order_does_not_matter(training: bool) -> None:
    # float64, so that the sums over reordered neighbours agree to rounding, not to float32 luck
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = PocoModel("tiny")
    randomise_(model, 6)
    model = model.double()
    model.train(training)
    pts = sphere_points(800, 7, batch=2).double()
    queries = box_queries(400, 8, batch=2).double()
    tables = model.tables(pts, 9, queries=queries)
    shuffled = permute_neighbours(tables, 10)
    assert not torch.equal(shuffled["ids00"], tables["ids00"])
    assert not torch.equal(shuffled["proj_indices"], tables["proj_indices"])
    first = copy.deepcopy(model)  # train mode updates norm_radius: run both from the same state
    a = first(pts, model.features(pts), tables, queries, tables["proj_indices"])
    b = model(pts, model.features(pts), shuffled, queries, shuffled["proj_indices"])
    assert (a - b).abs().max().item() <= 1e-10 * max(1.0, a.abs().max().item())


# --------------------------------------------------------------------------------------------------
# Quantized sampling


def plane_points(side: int = 100, seed: int = 0) -> torch.Tensor:
    """A dense jittered grid on the unit square of the plane z = 0, (3, side^2)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.linspace(0.0, 1.0, side)
    xx, yy = torch.meshgrid(u, u, indexing="ij")
    pts = torch.stack([xx.flatten(), yy.flatten(), torch.zeros(side * side)])
    pts[:2] += 0.004 * torch.rand(2, side * side, generator=g)
    return pts


def coverage_radius(points: torch.Tensor, chosen: torch.Tensor) -> float:
    """Largest distance from a point to its nearest chosen point."""
    distances, _ = cKDTree(points[:, chosen].T.numpy()).query(points.T.numpy())
    return float(distances.max())


def test_quantized_sampling_counts_and_determinism() -> None:
    pts = sphere_points(3000, 11)[0]
    for n in (1, 11, 750, 2999):
        idx = quantized_sampling(pts, n, torch.Generator().manual_seed(0))
        assert idx.dtype == torch.int64 and idx.shape == (n,)
        assert idx.unique().numel() == n and int(idx.min()) >= 0 and int(idx.max()) < 3000
    assert torch.equal(quantized_sampling(pts, 3000, 0), torch.arange(3000))
    same = [quantized_sampling(pts, 750, torch.Generator().manual_seed(42)) for _ in range(2)]
    assert torch.equal(same[0], same[1])
    assert not torch.equal(same[0], quantized_sampling(pts, 750, torch.Generator().manual_seed(43)))
    # numpy generators and int seeds are accepted and deterministic as well.
    a = quantized_sampling(pts, 200, np.random.default_rng(5))
    assert torch.equal(a, quantized_sampling(pts, 200, np.random.default_rng(5)))
    assert torch.equal(quantized_sampling(pts, 200, 5), quantized_sampling(pts, 200, 5))
    # Coincident points (inputs are drawn with replacement) still give n distinct indices.
    assert quantized_sampling(torch.zeros(3, 50), 10, 0).unique().numel() == 10
    doubled = torch.cat([pts[:, :100], pts[:, :100]], dim=1)
    assert quantized_sampling(doubled, 150, 0).unique().numel() == 150
    with pytest.raises(ValueError):
        quantized_sampling(pts, 3001, 0)
    assert level_sizes(3000) == [3000, 750, 187, 46, 11]
    assert level_sizes(2048) == [2048, 512, 128, 32, 8]
    assert level_sizes(10240) == [10240, 2560, 640, 160, 40]


def test_quantized_sampling_spreads_points() -> None:
    pts = plane_points()
    g = torch.Generator().manual_seed(12)
    n = 400
    spacing = 1.0 / np.sqrt(n)  # of a perfect n-point grid on the square
    quantized, uniform = [], []
    for _ in range(4):
        chosen = quantized_sampling(pts, n, g)
        lo, hi = pts[:2, chosen].min(dim=1).values, pts[:2, chosen].max(dim=1).values
        assert bool((lo < 0.05).all()) and bool((hi > 0.95).all())  # the chosen points span the square
        quantized.append(coverage_radius(pts, chosen))
        uniform.append(coverage_radius(pts, torch.randperm(pts.shape[1], generator=g)[:n]))
    assert max(quantized) < 2.0 * spacing
    assert np.mean(quantized) < np.mean(uniform)


# --------------------------------------------------------------------------------------------------
# kNN and the table set


def brute_force_distances(source: np.ndarray, target: np.ndarray, k: int) -> np.ndarray:
    """Sorted distances (M, k) from each target to its k nearest sources, float64."""
    d = np.sqrt(((target[:, None, :] - source[None, :, :]) ** 2).sum(-1))
    return np.sort(d, axis=1)[:, :k]


BACKENDS = ["scipy", "torch", pytest.param("pykdtree", marks=pytest.mark.skipif(
    not pykdtree_available(), reason="pykdtree not installed"))]  # fmt: skip


@pytest.mark.parametrize("backend", BACKENDS)
def test_knn_matches_brute_force(backend: KnnBackend) -> None:
    g = torch.Generator().manual_seed(13)
    source = torch.rand(2, 3, 700, generator=g)
    target = torch.rand(2, 3, 300, generator=g)
    for k in (1, 16, 64):
        index = knn(source, target, k, backend=backend)
        assert index.shape == (2, 300, k) and index.dtype == torch.int64
        for b in range(2):
            src, dst = source[b].T.double().numpy(), target[b].T.double().numpy()
            got = np.sqrt(((dst[:, None, :] - src[index[b].numpy()]) ** 2).sum(-1))
            np.testing.assert_allclose(np.sort(got, axis=1), brute_force_distances(src, dst, k), atol=1e-6)
            if backend != "torch":  # exact trees: same sets (no ties in random data)
                exact = np.argsort(((dst[:, None, :] - src[None]) ** 2).sum(-1), axis=1)[:, :k]
                assert (np.sort(index[b].numpy(), axis=1) == np.sort(exact, axis=1)).all()
    # A point finds itself; k is clipped to the source size; unbatched input works.
    self_index = knn(source, source, 4, backend=backend)
    assert torch.equal(self_index[:, :, 0], torch.arange(700).expand(2, -1))
    assert knn(source[:, :, :5], target, 16, backend=backend).shape == (2, 300, 5)
    assert knn(source[0], target[0], 3, backend=backend).shape == (300, 3)


def _ordered_by_hand(source: torch.Tensor, target: torch.Tensor, k: int) -> np.ndarray:
    """(distance, index) order by Python's own sort over exact float64 sums: the definition, slowly."""
    src, dst = source.double().numpy(), target.double().numpy()
    out = np.empty((dst.shape[1], min(k, src.shape[1])), dtype=np.int64)
    for j in range(dst.shape[1]):
        keys = []
        for i in range(src.shape[1]):
            dx, dy, dz = (dst[:, j] - src[:, i]).tolist()
            keys.append(((dx * dx + dy * dy) + dz * dz, i))
        out[j] = [i for _, i in sorted(keys)[: out.shape[1]]]
    return out


def test_ordered_knn_is_one_answer_on_every_path_with_ties() -> None:
    """Grid clouds (exact ties everywhere, duplicate points too): the CPU tree path, the brute path a GPU
    runs (here on the CPU) and a hand sort by (squared distance, index) give the same tables, order
    included; random clouds agree with the other exact backends' sets."""
    from datagen.pipeline.refine.poco.spatial import _knn_ordered_brute, _knn_ordered_tree, knn_ordered

    g = torch.Generator().manual_seed(5)
    for cells, n_source, n_target, k in ((4, 300, 200, 32), (6, 200, 150, 16), (3, 40, 60, 1), (8, 90, 50, 64)):
        source = torch.randint(0, cells, (2, 3, n_source), generator=g).float() * 0.25 - 0.5
        target = torch.randint(0, 2 * cells, (2, 3, n_target), generator=g).float() * 0.125 - 0.5
        tree, brute = _knn_ordered_tree(source, target, k), _knn_ordered_brute(source, target, k)
        assert tree.shape == (2, n_target, min(k, n_source)) and torch.equal(tree, brute)
        assert torch.equal(knn(source, target, k, backend="ordered"), tree)
        assert torch.equal(knn_ordered(source, target, k), tree)
        for b in range(2):
            assert (tree[b].numpy() == _ordered_by_hand(source[b], target[b], k)).all()
    source, target = torch.rand(1, 3, 2000, generator=g), torch.rand(1, 3, 700, generator=g)
    ordered = knn_ordered(source, target, 16)
    reference = knn(source, target, 16, backend="scipy")
    assert (np.sort(ordered.numpy(), axis=2) == np.sort(reference.numpy(), axis=2)).all()
    assert torch.equal(knn_ordered(source, source, 1)[0, :, 0], torch.arange(2000))


def test_ordered_knn_is_the_same_whichever_tree_proposes(monkeypatch: pytest.MonkeyPatch) -> None:
    """The tree only proposes candidates: scipy's cKDTree (no pykdtree installed) gives pykdtree's tables."""
    from datagen.pipeline.refine.poco import spatial

    g = torch.Generator().manual_seed(9)
    source = torch.randint(0, 5, (1, 3, 400), generator=g).float() * 0.2
    target = torch.randint(0, 10, (1, 3, 300), generator=g).float() * 0.1
    first = spatial.knn_ordered(source, target, 24)
    installed = spatial.pykdtree_available()
    monkeypatch.setattr(spatial, "pykdtree_available", lambda: not installed)
    assert torch.equal(spatial.knn_ordered(source, target, 24), first)


def test_spatial_tables() -> None:
    pts = sphere_points(3000, 14, batch=2)
    queries = box_queries(500, 15, batch=2)
    tables = spatial_tables(pts, torch.Generator().manual_seed(1), queries=queries, decoder_k=64)
    again = spatial_tables(pts, torch.Generator().manual_seed(1), queries=queries, decoder_k=64)
    assert tables.keys() == again.keys()
    assert all(torch.equal(tables[key], again[key]) for key in tables)
    sizes = level_sizes(3000)
    for level in range(1, 5):
        sample = tables[f"sample{level}"]
        assert sample.shape == (2, sizes[level])
        assert all(sample[b].unique().numel() == sizes[level] for b in range(2))
        assert int(sample.max()) < sizes[level - 1]
    expected = {f"ids{a}{b}": (sizes[b], min(16, sizes[a])) for a, b in CONV_TABLES}
    expected.update({"ids43": (46, 1), "ids32": (187, 1), "ids21": (750, 1), "ids10": (3000, 1)})
    for name, (rows, k) in expected.items():
        assert tables[name].shape == (2, rows, k), name
    assert tables["proj_indices"].shape == (2, 500, 64)
    levels = level_points(pts, tables)
    # Spot check against brute force: the upsampling table points each level-1 point at its nearest level-2 one.
    for b in range(2):
        fine, coarse = levels[1][b].T.numpy(), levels[2][b].T.numpy()
        nearest = np.argmin(((fine[:, None] - coarse[None]) ** 2).sum(-1), axis=1)
        assert (tables["ids21"][b, :, 0].numpy() == nearest).all()
        # Supports are their own nearest neighbours in the same-level tables.
        assert torch.equal(tables["ids11"][b, :, 0], torch.arange(750))


# --------------------------------------------------------------------------------------------------
# Forward passes


def test_official_forward(official: PocoModel) -> None:
    pts = sphere_points(3000, 16)
    queries = box_queries(2048, 17)
    tables = official.tables(pts, 0, queries=queries)
    with torch.no_grad():
        latents = official.encode(pts, official.features(pts), tables)
        logits = official.decode(latents, pts, queries, tables["proj_indices"])
    assert latents.shape == (1, 32, 3000)
    assert logits.shape == (1, 2, 2048) and bool(torch.isfinite(logits).all())


def test_training_step_and_norm_radius() -> None:
    model = PocoModel("tiny").train()
    pts = sphere_points(1000, 18, batch=2)
    queries = box_queries(256, 19, batch=2)
    tables = model.tables(pts, 1, queries=queries)
    # The first FKAConv's running radius moves 10% towards the mean neighbourhood radius.
    local = torch.gather(pts, 2, tables["ids00"].reshape(2, 1, -1).expand(-1, 3, -1)).view(2, 3, 1000, 16)
    mean_radius = (local - pts.unsqueeze(3)).norm(dim=1).max(dim=2).values.mean()
    logits = model(pts, model.features(pts), tables, queries, tables["proj_indices"])
    assert torch.allclose(model.net.cv0.norm_radius, 0.9 + 0.1 * mean_radius)
    labels = (queries.norm(dim=1) < 0.4).long()
    nn.functional.cross_entropy(logits, labels).backward()
    assert model.net.cv0.cv.weight.grad is not None and model.projection.fc8.weight.grad is not None
    # The dead branch gets no gradient, exactly as in the release.
    assert model.net.cv5.weight.grad is None and model.net.bn5.weight.grad is None


def test_direction_features() -> None:
    model = PocoModel("tiny_sv").eval()
    pts = sphere_points(600, 20)
    camera = torch.tensor([2.0, 0.0, 0.5]).view(1, 3, 1)
    features = model.features(pts, directions=camera - pts)
    assert features.shape == (1, 6, 600)
    assert torch.equal(features[:, :3], torch.ones(1, 3, 600))
    assert torch.allclose(features[:, 3:].norm(dim=1), torch.ones(1, 600))
    queries = box_queries(100, 21)
    tables = model.tables(pts, 2, queries=queries)
    assert model(pts, features, tables, queries, tables["proj_indices"]).shape == (1, 2, 100)
    with pytest.raises(ValueError):
        model.features(pts)


def test_fkaconv_matches_conv2d_layout() -> None:
    """The channels-last slot projection equals the release's (B, Cin, M, S) matmul + Conv2d form."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(1)
        conv = FKAConv(5, 7)
    randomise_(conv, 2)
    conv.eval()
    g = torch.Generator().manual_seed(3)
    pos, x = torch.rand(2, 3, 300, generator=g), torch.randn(2, 5, 300, generator=g)
    support = pos[:, :, :80]
    index = knn(pos, support, 16)
    local = gather_neighbours(pos, index) - support.unsqueeze(3)
    distances = local.norm(dim=1)
    weight = torch.sigmoid(-conv.alpha * distances + conv.beta)
    weight = (weight / (weight.sum(2, keepdim=True) + 1e-6) * 16).unsqueeze(1)
    mat = nn.functional.relu(conv.bn1(conv.fc1(local / conv.norm_radius)))
    mat = torch.cat([mat, (mat * weight).amax(3, keepdim=True).expand_as(mat)], dim=1)
    mat = nn.functional.relu(conv.bn2(conv.fc2(mat)))
    mat = torch.cat([mat, (mat * weight).amax(3, keepdim=True).expand_as(mat)], dim=1)
    mat = nn.functional.relu(conv.fc3(mat)) * weight
    slots = torch.matmul(gather_neighbours(x, index).transpose(1, 2), mat.permute(0, 2, 3, 1)).transpose(1, 2)
    expected = conv.cv(slots).squeeze(3)
    got = conv(x, pos, support, index)
    assert got.shape == (2, 7, 80)
    assert (got - expected).abs().max().item() <= 1e-5 * max(1.0, expected.abs().max().item())
