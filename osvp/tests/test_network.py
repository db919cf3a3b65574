"""The OSVP network's shapes, gradients, determinism and presets; its sampling helpers by hand."""

from __future__ import annotations

import pytest
import torch
from osvp.network import PRESETS, NetworkPreset, build_network, farthest_point_sample, nearest_neighbours


def cloud(batch: int, points: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(batch, points, 3, generator=generator) * 0.05


def states(batch: int, views: int) -> torch.Tensor:
    state = torch.zeros(batch, views)
    state[torch.arange(batch), torch.arange(batch) % views] = 1.0
    return state


@pytest.mark.parametrize(("preset", "batch", "points"), [("paper", 2, 2048), ("small", 4, 1024)])
def test_forward_and_backward_shapes(preset: str, batch: int, points: int) -> None:
    network = build_network(preset, 32)
    logits = network(cloud(batch, points), states(batch, 32))
    assert logits.shape == (batch, 32) and torch.isfinite(logits).all()
    logits.sum().backward()
    missing = [name for name, p in network.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()]
    assert not missing


def test_the_paper_preset_has_the_papers_sizes() -> None:
    paper = PRESETS["paper"]
    sizes = (paper.num_points, paper.centres, paper.neighbours, paper.embed_dim, paper.depth)
    assert sizes == (2048, (512, 256), 16, 384, 6)
    assert (paper.view_layers, paper.view_heads, paper.feature_dim) == (4, 4, 1024)
    head = build_network("paper", 32).head
    assert [m.out_features for m in head if isinstance(m, torch.nn.Linear)] == [1024, 1024, 32]


def test_any_view_count_and_any_point_count() -> None:
    network = build_network("small", 20)
    assert network(cloud(3, 300), states(3, 20)).shape == (3, 20)
    assert network(cloud(1, 5), states(1, 20)).shape == (1, 20)  # fewer points than centres or neighbours
    with pytest.raises(ValueError, match="view_state must be"):
        network(cloud(3, 300), states(3, 32))


def test_eval_is_deterministic_and_the_view_state_matters() -> None:
    network = build_network("small", 32).eval()
    points = cloud(2, 1024)
    with torch.no_grad():
        first = network(points, states(2, 32))
        second = network(points, states(2, 32))
        other = network(points, torch.roll(states(2, 32), 5, dims=1))
    assert torch.equal(first, second)
    assert not torch.allclose(first, other)


@pytest.mark.parametrize("preset", ["paper", "small"])
def test_the_point_cloud_encoder_is_the_same_in_train_and_eval_mode(preset: str) -> None:
    """No dropout in the point transformer: with it, a trained network's eval-mode output (what
    validation and planning see) blew up on small clouds that training mode handled."""
    torch.manual_seed(0)
    encoder = build_network(preset, 8).cloud
    points = cloud(2, PRESETS[preset].num_points)
    with torch.no_grad():
        trained = encoder.train()(points)
        evaluated = encoder.eval()(points)
    torch.testing.assert_close(trained, evaluated)


def test_preset_round_trip_and_refusals() -> None:
    for preset in PRESETS.values():
        assert NetworkPreset.from_dict(preset.as_dict()) == preset
    broken = PRESETS["small"].as_dict() | {"heads": 5}
    with pytest.raises(ValueError, match="divide"):
        NetworkPreset.from_dict(broken)
    with pytest.raises(ValueError, match="exactly"):
        NetworkPreset.from_dict({"name": "x"})
    with pytest.raises(ValueError, match="unknown preset 'huge'"):
        build_network("huge", 32)


def test_farthest_point_sample_on_a_line_takes_both_ends_first() -> None:
    xs = torch.tensor([0.3, 0.0, 1.0, 0.5, 0.9, 0.1])
    points = torch.stack([xs, torch.zeros(6), torch.zeros(6)], dim=1)[None]
    chosen = farthest_point_sample(points, 3)[0].tolist()
    # from index 0 (x = 0.3): farthest is x = 1.0 (index 2), then x = 0.0 (index 1)
    assert chosen == [0, 2, 1]
    assert farthest_point_sample(points, 10).shape == (1, 6)


def test_nearest_neighbours_by_hand() -> None:
    points = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [6.0, 0, 0]]])
    queries = torch.tensor([[[2.9, 0, 0], [0.2, 0, 0]]])
    found = nearest_neighbours(queries, points, 2)[0]
    assert found[0].tolist() == [2, 1] and found[1].tolist() == [0, 1]


@pytest.mark.parametrize("family", ["nbvnet", "scvp"])
def test_grid_networks_map_a_grid_to_one_logit_per_view(family: str) -> None:
    """NBVNet's body: three conv-ReLU-pool blocks take 32^3 to 4^3; SCVP joins the view state after
    them, NBVNet ignores it (its masked classification needs only the grid)."""
    from osvp.architectures import architecture

    chosen = architecture(family)
    network = chosen.build(chosen.preset("paper"), 32).eval()
    grid = torch.rand(3, 32, 32, 32, generator=torch.Generator().manual_seed(1))
    state = torch.zeros(3, 32)
    logits = network(grid, state)
    assert logits.shape == (3, 32) and torch.isfinite(logits).all()
    state[:, 5] = 1.0
    changed = not torch.allclose(network(grid, state), logits)
    assert changed == (family == "scvp")
    assert chosen.reads == "grid" and chosen.preset("paper").num_points == 1
    assert network.head[0].in_features == 8 * 4**3 + (32 if family == "scvp" else 0)
    logits.sum().backward()
    with pytest.raises(ValueError, match=r"grid must be \(B, 32, 32, 32\)"):
        network(torch.zeros(3, 16, 16, 16), state)


def test_grid_presets_round_trip_and_refusals() -> None:
    from osvp.grid_network import NBVNET_PRESETS, SCVP_PRESETS, GridPreset

    for preset in (*NBVNET_PRESETS.values(), *SCVP_PRESETS.values()):
        assert GridPreset.from_dict(preset.as_dict()) == preset
    assert NBVNET_PRESETS["paper"].channels == (10, 12, 8) and NBVNET_PRESETS["paper"].hidden == (1500, 500, 100)
    broken = {**NBVNET_PRESETS["small"].as_dict(), "channels": [10, 0, 8]}
    with pytest.raises(ValueError, match="positive whole number"):
        GridPreset.from_dict(broken)
    with pytest.raises(ValueError, match="needs exactly"):
        GridPreset.from_dict({"name": "x"})


def test_every_architecture_has_the_same_preset_names_and_a_default_target() -> None:
    from osvp.architectures import ARCHITECTURES, architecture
    from osvp.loss import targets

    assert sorted(ARCHITECTURES) == ["nbvnet", "osvp", "scvp"]
    for family in ARCHITECTURES.values():
        assert sorted(family.presets) == ["paper", "small"] and family.default_target in targets()
    with pytest.raises(ValueError, match="unknown network 'pointnet'; choose one of osvp, nbvnet, scvp"):
        architecture("pointnet")
