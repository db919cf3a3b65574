"""SCLoss against values computed by hand from the paper's equation 3, and the targets that allow for
equally good covers (marginal, mincover, support) against hand-computed values."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from osvp.loss import ambiguity_targets, marginal_loss, mincover_loss, sc_loss, support_loss, target_loss, targets


def probability_loss(p: list[list[float]], g: list[list[float]], lam: float) -> float:
    """Equation 3 term by term in plain Python, from probabilities."""
    per_sample = []
    for ps, gs in zip(p, g, strict=True):
        terms = []
        for pi, gi in zip(ps, gs, strict=True):
            ce = gi * math.log(pi) + (1 - gi) * math.log(1 - pi)
            terms.append((1 - gi) * ce + lam * gi * ce)
        per_sample.append(-sum(terms) / len(terms))
    return sum(per_sample) / len(per_sample)


def test_a_hand_computed_value() -> None:
    # one sample, two views: p = (0.8, 0.4), g = (1, 0), lambda 1.25
    # CE = (ln 0.8, ln 0.6); SCLoss = -(1.25 ln 0.8 + ln 0.6) / 2 = 0.3948775...
    logits = torch.logit(torch.tensor([[0.8, 0.4]], dtype=torch.float64))
    value = float(sc_loss(logits, torch.tensor([[1.0, 0.0]], dtype=torch.float64), 1.25))
    assert value == pytest.approx(-(1.25 * math.log(0.8) + math.log(0.6)) / 2, rel=1e-12)
    assert value == pytest.approx(0.3948775315, rel=1e-9)


@pytest.mark.parametrize("lam", [0.75, 1.0, 1.25, 2.0])
def test_matches_the_equation_on_a_batch(lam: float) -> None:
    p = [[0.9, 0.2, 0.5, 0.7], [0.1, 0.6, 0.3, 0.95]]
    g = [[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0]]
    logits = torch.logit(torch.tensor(p, dtype=torch.float64))
    value = float(sc_loss(logits, torch.tensor(g, dtype=torch.float64), lam))
    assert value == pytest.approx(probability_loss(p, g, lam), rel=1e-12)


def test_lambda_one_is_plain_binary_cross_entropy_and_ones_weigh_more_above_one() -> None:
    logits = torch.tensor([[0.3, -1.2, 2.0]])
    labels = torch.tensor([[1.0, 0.0, 1.0]])
    bce = torch.nn.functional.binary_cross_entropy_with_logits(logits, labels)
    assert float(sc_loss(logits, labels, 1.0)) == pytest.approx(float(bce), rel=1e-6)
    assert float(sc_loss(logits, labels, 2.0)) > float(sc_loss(logits, labels, 1.0))


def test_refuses_mismatched_shapes_and_bad_lambda() -> None:
    with pytest.raises(ValueError, match="one shape"):
        sc_loss(torch.zeros(2, 3), torch.zeros(2, 4))
    with pytest.raises(ValueError, match="positive"):
        sc_loss(torch.zeros(1, 3), torch.zeros(1, 3), 0.0)


def probabilities_to_logits(p: list[list[float]]) -> torch.Tensor:
    return torch.logit(torch.tensor(p, dtype=torch.float64))


def test_marginal_target_by_hand() -> None:
    # p = (0.8, 0.4), marginals q = (0.5, 0.25), lambda 2:
    # view 0: 2 * 0.5 * -ln 0.8 + 0.5 * -ln 0.2 = 0.223144 + 0.804719 = 1.027863
    # view 1: 2 * 0.25 * -ln 0.4 + 0.75 * -ln 0.6 = 0.458145 + 0.383119 = 0.841265
    # mean over the two views: 0.934564
    value = float(marginal_loss(probabilities_to_logits([[0.8, 0.4]]), torch.tensor([[0.5, 0.25]]), 2.0))
    assert value == pytest.approx(0.9345635456, rel=1e-9)


def test_marginal_target_with_hard_marginals_is_scloss() -> None:
    logits = probabilities_to_logits([[0.9, 0.2, 0.5], [0.3, 0.6, 0.95]])
    bits = torch.tensor([[1.0, 0.0, 1.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert float(marginal_loss(logits, bits, 1.25)) == pytest.approx(float(sc_loss(logits, bits, 1.25)), rel=1e-12)


def test_mincover_target_takes_each_samples_nearest_cover_by_hand() -> None:
    # lambda 1.25, three views; per cover SCLoss = (1/3) sum [1.25 g (-ln p) + (1 - g)(-ln(1 - p))]
    # sample A, p = (0.8, 0.4, 0.3), covers {0} and {1}:
    #   {0}: (1.25 * 0.223144 + 0.510826 + 0.356675) / 3 = 0.382143
    #   {1}: (1.609438 + 1.25 * 0.916291 + 0.356675) / 3 = 1.037159  -> min 0.382143
    # sample B, p = (0.1, 0.7, 0.6), covers {1, 2}, {0, 2} and a padding slot:
    #   {1, 2}: (0.105361 + 1.25 * 0.356675 + 1.25 * 0.510826) / 3 = 0.396579
    #   {0, 2}: (1.25 * 2.302585 + 1.203973 + 1.25 * 0.510826) / 3 = 1.573579  -> min 0.396579
    # batch mean (0.382143 + 0.396579) / 2 = 0.389361
    logits = probabilities_to_logits([[0.8, 0.4, 0.3], [0.1, 0.7, 0.6]])
    covers = torch.tensor(
        [[[1, 0, 0], [0, 1, 0], [0, 0, 0]], [[0, 1, 1], [1, 0, 1], [1, 1, 1]]], dtype=torch.float64
    )  # the last slot of each sample is padding: never chosen, however cheap
    valid = torch.tensor([[True, True, False], [True, True, False]])
    assert float(mincover_loss(logits, covers, valid, 1.25)) == pytest.approx(0.3893610387, rel=1e-9)
    # Only the second covers: (1.037159 + 1.573579) / 2 = 1.305369. The padding slots would be cheaper
    # ({} for A: (1.609438 + 0.510826 + 0.356675) / 3 = 0.825646; {0, 1, 2} for B: 1.320869): masked out.
    only_second = torch.tensor([[False, True, False], [False, True, False]])
    assert float(mincover_loss(logits, covers, only_second, 1.25)) == pytest.approx(1.3053687452, rel=1e-9)
    one = mincover_loss(logits, covers[:, :1], valid[:, :1], 1.25)  # a single cover is plain SCLoss
    assert float(one) == pytest.approx(float(sc_loss(logits, covers[:, 0], 1.25)), rel=1e-12)


def test_mincover_target_refuses_a_sample_without_covers() -> None:
    with pytest.raises(ValueError, match="at least one cover"):
        mincover_loss(torch.zeros(2, 3), torch.zeros(2, 1, 3), torch.tensor([[True], [False]]))


def test_support_target_excuses_the_other_covers_views_by_hand() -> None:
    # p = (0.8, 0.4, 0.7), label {0}, support {0, 2}, lambda 1.25:
    # view 0: 1.25 * -ln 0.8 = 0.278929; view 1: -ln 0.6 = 0.510826; view 2: weight 0
    # mean over the three views: (0.278929 + 0.510826) / 3 = 0.263252
    logits = probabilities_to_logits([[0.8, 0.4, 0.7]])
    label, support = torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 1.0]])
    assert float(support_loss(logits, label, support, 1.25)) == pytest.approx(0.2632516876, rel=1e-9)
    assert float(support_loss(logits, label, label, 1.25)) == pytest.approx(float(sc_loss(logits, label, 1.25)))


def test_target_loss_dispatches_and_names_what_is_missing() -> None:
    logits = probabilities_to_logits([[0.8, 0.4, 0.7]])
    label = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    batch = SimpleNamespace(
        label=label, marginals=None, support=None, covers=None, cover_mask=None, view_gain=None, best_view=None
    )
    assert float(target_loss("label", logits, batch, 1.25)) == pytest.approx(float(sc_loss(logits, label, 1.25)))
    for target, missing in (("marginal", "marginals"), ("mincover", "covers"), ("support", "support")):
        with pytest.raises(ValueError, match=f"target '{target}' needs the batch's {missing}"):
            target_loss(target, logits, batch, 1.25)
    with pytest.raises(ValueError, match=r"target 'gain' needs every view's gain \(a version-3 dataset\)"):
        target_loss("gain", logits, batch, 1.25)
    with pytest.raises(ValueError, match=r"target 'best_view' needs every sample's best next view \(a version-3"):
        target_loss("best_view", logits, batch, 1.25)
    with pytest.raises(ValueError, match="unknown training target 'nope'; choose one of label, marginal, mincover"):
        target_loss("nope", logits, batch, 1.25)
    with pytest.raises(ValueError, match=r"target 'near_best' needs every view's gain \(a version-3 dataset\)"):
        target_loss("near_best", logits, batch, 1.25)
    assert set(targets()) - set(ambiguity_targets()) == {"label", "gain", "best_view", "near_best"}


def test_the_gain_target_is_the_mean_squared_error_of_the_predicted_shares() -> None:
    from osvp.loss import gain_loss

    logits = torch.tensor([[0.0, 2.0, -1.0], [1.0, -3.0, 0.5]])
    gains = torch.tensor([[0.5, 0.2, 0.0], [0.1, 0.0, 0.9]])
    expected = ((torch.sigmoid(logits) - gains) ** 2).mean()
    assert torch.allclose(gain_loss(logits, gains), expected)
    assert float(gain_loss(torch.full((1, 3), -40.0), torch.zeros(1, 3))) < 1e-12


def test_the_best_view_target_is_the_cross_entropy_of_the_class_among_the_open_views_by_hand() -> None:
    """NBVNet's classification, with the views taken masked out: the softmax runs over the open views
    only, and a case without a next view (best view -1) adds nothing."""
    from osvp.loss import best_view_loss

    logits = torch.tensor([[1.0, 2.0, 0.5, -1.0], [0.0, 0.3, 3.0, 1.0], [5.0, 1.0, 1.0, 1.0]], dtype=torch.float64)
    state = torch.tensor([[0, 1, 0, 0], [1, 0, 0, 0], [1, 1, 1, 1]], dtype=torch.float64)
    best = torch.tensor([0, 3, -1])
    # sample 0: open views 0, 2, 3 -> -log(e^1 / (e^1 + e^0.5 + e^-1)); sample 1: open 1, 2, 3 -> view 3
    first = -math.log(math.exp(1.0) / (math.exp(1.0) + math.exp(0.5) + math.exp(-1.0)))
    second = -math.log(math.exp(1.0) / (math.exp(0.3) + math.exp(3.0) + math.exp(1.0)))
    assert float(best_view_loss(logits, state, best)) == pytest.approx((first + second) / 2, rel=1e-12)
    none = best_view_loss(logits[2:], state[2:], best[2:])
    assert float(none) == 0.0 and none.requires_grad is False
    trainable = logits.clone().requires_grad_(True)
    best_view_loss(trainable, state, best).backward()
    assert (
        trainable.grad is not None
        and float(trainable.grad[0, 1]) == 0.0
        and float(trainable.grad[2].abs().sum()) == 0.0
    )


def test_the_near_best_target_weighs_each_open_view_by_its_gain_against_the_best_by_hand() -> None:
    """Soft classes exp((g - g_best) / (0.1 g_best)) over the open views; a view that sees nothing new
    next to one that does is (almost) NBVNet's class; scaling every gain changes nothing; a case with
    nothing left adds nothing."""
    from osvp.loss import best_view_loss, near_best_loss

    logits = torch.tensor([[1.0, 2.0, 0.5, -1.0], [0.0, 0.3, 3.0, 1.0], [5.0, 1.0, 1.0, 1.0]], dtype=torch.float64)
    state = torch.tensor([[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 0]], dtype=torch.float64)
    gains = torch.tensor([[0.2, 0.5, 0.18, 0.0], [0.9, 0.1, 0.1, 0.05], [0, 0, 0, 0]], dtype=torch.float64)
    # sample 0: open views 0, 2, 3 with gains 0.2, 0.18, 0 -> weights 1, e^-1, e^-10
    weights = [1.0, math.exp(-1.0), math.exp(-10.0)]
    soft = [w / sum(weights) for w in weights]
    log_p = [v - math.log(sum(math.exp(x) for x in (1.0, 0.5, -1.0))) for v in (1.0, 0.5, -1.0)]
    first = -sum(q * lp for q, lp in zip(soft, log_p, strict=True))
    # sample 1: open views 1, 2, 3 with gains 0.1, 0.1, 0.05 -> weights 1, 1, e^-5 (view 0, taken, is ignored)
    weights = [1.0, 1.0, math.exp(-5.0)]
    soft = [w / sum(weights) for w in weights]
    log_p = [v - math.log(sum(math.exp(x) for x in (0.3, 3.0, 1.0))) for v in (0.3, 3.0, 1.0)]
    second = -sum(q * lp for q, lp in zip(soft, log_p, strict=True))
    assert float(near_best_loss(logits, state, gains)) == pytest.approx((first + second) / 2, rel=1e-9)
    assert float(near_best_loss(logits, state, 3.0 * gains)) == pytest.approx((first + second) / 2, rel=1e-9)
    one_hot = torch.tensor([[0.0, 0.0, 0.4, 0.0]], dtype=torch.float64)
    alone = near_best_loss(logits[:1], state[:1], one_hot)
    assert float(alone) == pytest.approx(float(best_view_loss(logits[:1], state[:1], torch.tensor([2]))), rel=1e-4)
    assert float(near_best_loss(logits[2:], state[2:], gains[2:])) == 0.0
