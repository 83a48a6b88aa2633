"""DQN loss (eqs. 8-9) and HSCL (eq. 13): values by hand, input checks, and HSCL alone teaching the expert."""
from __future__ import annotations

import math

import pytest
import torch

from mapf_policy.losses import combined_loss, dqn_loss, expert_agreement, hot_vectors, hscl_loss


def test_dqn_loss_by_hand_with_terminal_handling():
    q = torch.tensor([[1.0, 2.0, 0.0, 0.0, 0.0], [0.5, 0.0, 0.0, 0.0, 0.0]])
    nxt = torch.tensor([[0.0, 4.0, 1.0, 0.0, 0.0], [9.0, 0.0, 0.0, 0.0, 0.0]])
    loss = dqn_loss(q, torch.tensor([1, 0]), torch.tensor([-0.5, 3.0]), nxt, torch.tensor([False, True]), 0.9)
    # row 0: target -0.5 + 0.9 * max(next) = 3.1, Q = 2 ; row 1: terminal -> target 3.0, Q = 0.5
    expected = ((3.1 - 2.0) ** 2 + (3.0 - 0.5) ** 2) / 2
    assert loss.item() == pytest.approx(expected, rel=1e-6)


def test_dqn_loss_has_no_gradient_through_the_target():
    q = torch.zeros(3, 5, requires_grad=True)
    nxt = torch.ones(3, 5, requires_grad=True)
    dqn_loss(q, torch.tensor([0, 1, 2]), torch.zeros(3), nxt, torch.zeros(3, dtype=torch.bool), 0.99).backward()
    assert nxt.grad is None and q.grad is not None


def test_dqn_loss_input_checks():
    q = torch.zeros(2, 5)
    with pytest.raises(ValueError, match="actions"):
        dqn_loss(q, torch.tensor([0, 5]), torch.zeros(2), q, torch.zeros(2, dtype=torch.bool), 0.9)
    with pytest.raises(ValueError, match="rewards"):
        dqn_loss(q, torch.tensor([0, 1]), torch.zeros(3), q, torch.zeros(2, dtype=torch.bool), 0.9)
    with pytest.raises(ValueError, match="q must"):
        dqn_loss(torch.zeros(2, 4), torch.tensor([0, 1]), torch.zeros(2), q, torch.zeros(2, dtype=torch.bool), 0.9)


def test_hot_vectors_follow_table_one():
    h = hot_vectors(torch.tensor([2]), 0.1)
    assert torch.allclose(h, torch.tensor([[-0.1, -0.1, 0.9, -0.1, -0.1]]))
    for bad in (0.0, 0.2, -0.1):
        with pytest.raises(ValueError, match="tau_h"):
            hot_vectors(torch.tensor([0]), bad)


def test_hscl_matches_a_direct_loop_over_anchors_and_positives():
    torch.manual_seed(0)
    q = torch.randn(7, 5)
    labels = torch.tensor([0, 0, 3, 1, 3, 3, 4])
    tau, t = 0.15, 0.2
    h = hot_vectors(labels, tau)
    cos = lambda a, b: torch.dot(a, b) / (a.norm() * b.norm())  # noqa: E731
    total = 0.0
    for i in range(7):
        denom = sum(math.exp(cos(h[i], q[j]) / t) for j in range(7))
        pos = [p for p in range(7) if labels[p] == labels[i]]  # P(i) includes i (see losses.py)
        total += -sum(math.log(math.exp(cos(h[i], q[p]) / t) / denom) for p in pos) / len(pos)
    assert hscl_loss(q, labels, tau, t).item() == pytest.approx(total / 7, rel=1e-5)


def test_hscl_is_lower_when_q_points_at_the_expert_action():
    labels = torch.tensor([0, 1, 2, 3, 4, 1])
    good = hot_vectors(labels, 0.1) * 3.0
    bad = hot_vectors((labels + 1) % 5, 0.1) * 3.0
    assert hscl_loss(good, labels).item() < hscl_loss(bad, labels).item()


def test_minimising_hscl_alone_makes_argmax_q_agree_with_the_expert():
    """Tiny synthetic problem: a linear-ReLU Q-model, features from which the expert label is learnable."""
    g = torch.Generator().manual_seed(0)
    n, d = 256, 12
    x = torch.randn(n, d, generator=g)
    labels = (x[:, :5] + 0.3 * torch.randn(n, 5, generator=g)).argmax(dim=1)
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(d, 32), torch.nn.ReLU(), torch.nn.Linear(32, 5))
    # Negative Q offsets as in MAPF (step rewards < 0), to show HSCL works on the direction of Q.
    with torch.no_grad():
        model[2].bias.fill_(-2.0)
    before = expert_agreement(model(x), labels)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(300):
        opt.zero_grad()
        hscl_loss(model(x), labels, tau_h=0.1, temperature=0.1).backward()
        opt.step()
    after = expert_agreement(model(x), labels)
    assert before < 0.5
    assert after > 0.9, f"argmax Q agrees with the expert on {after:.2f} of samples after HSCL training"


def test_hscl_input_checks_and_combined_loss():
    with pytest.raises(ValueError, match="expert_actions"):
        hscl_loss(torch.zeros(2, 5), torch.tensor([0, 7]))
    with pytest.raises(ValueError, match="temperature"):
        hscl_loss(torch.zeros(2, 5), torch.tensor([0, 1]), temperature=0.0)
    assert combined_loss(torch.tensor(2.0), torch.tensor(4.0), 0.5, 0.25).item() == pytest.approx(2.0)


def test_margin_loss_is_zero_once_the_expert_action_leads_by_the_margin_and_ignores_the_rest():
    from mapf_policy.losses import margin_loss

    a = torch.tensor([2, 0])
    q = torch.tensor([[0.0, -0.3, 0.2, 0.05, -0.9], [1.0, 0.5, 0.9, 0.0, 0.0]])
    # row 0: leads by 0.15 >= 0.1 -> 0; row 1: runner-up 0.9 + 0.1 - 1.0 = 0 -> 0
    assert float(margin_loss(q, a, 0.1)) == pytest.approx(0.0)
    # with margin 0.3: row 0 gives 0.05 + 0.3 - 0.2 = 0.15, row 1 gives 0.9 + 0.3 - 1.0 = 0.2
    assert float(margin_loss(q, a, 0.3)) == pytest.approx(0.175)
    q2 = q.clone()
    q2[0, 4], q2[0, 1] = 0.1, 0.1  # reorder the non-expert actions below the margin: no change
    assert float(margin_loss(q2, a, 0.1)) == pytest.approx(0.0)
    with pytest.raises(ValueError, match="margin"):
        margin_loss(q, a, 0.0)
