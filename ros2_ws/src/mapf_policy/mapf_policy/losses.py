"""The two losses of section IV: DQN (eqs. 8-9) and the hot supervised contrastive loss HSCL (eq. 13).

Conventions: Q-value tensors are (B, 5), actions are (B,) int64 in 0..4, rewards (B,) float.
Loss = delta * L1 + phi * L2 (eq. 14) is `combined_loss`.
"""
from __future__ import annotations

import torch
from torch.nn import functional as F

N_ACTIONS = 5


def _check_q(q: torch.Tensor, name: str) -> int:
    if q.dim() != 2 or q.shape[1] != N_ACTIONS:
        raise ValueError(f"{name} must have shape (B, {N_ACTIONS}), got {tuple(q.shape)}")
    return q.shape[0]


def _check_vec(x: torch.Tensor, b: int, name: str) -> None:
    if tuple(x.shape) != (b,):
        raise ValueError(f"{name} must have shape ({b},), got {tuple(x.shape)}")


def _check_actions(a: torch.Tensor, b: int, name: str) -> None:
    _check_vec(a, b, name)
    if a.numel() and (int(a.min()) < 0 or int(a.max()) >= N_ACTIONS):
        raise ValueError(f"{name} must lie in 0..{N_ACTIONS - 1}, got {a.min().item()}..{a.max().item()}")


def _check_expert_batch(q: torch.Tensor, expert_actions: torch.Tensor, loss: str) -> int:
    """Rows of an imitation term's batch: q (B, 5) and expert_actions (B,) checked, B >= 1."""
    b = _check_q(q, "q")
    _check_actions(expert_actions, b, "expert_actions")
    if b == 0:
        raise ValueError(f"{loss} needs at least one expert sample")
    return b


def dqn_loss(
    q: torch.Tensor,
    actions: torch.Tensor,
    rewards: torch.Tensor,
    next_q_target: torch.Tensor,
    terminated: torch.Tensor,
    gamma: float | torch.Tensor,
) -> torch.Tensor:
    """L1 = mean (TargetQ - Q(s, a))^2 with TargetQ = r + gamma * max_a' Q(s', a'; theta_target).

    Eq. (8) writes Q(s, a') but means the next state s' (eq. 7). `next_q_target` comes from the target
    network and carries no gradient. `terminated` (B,) bool marks transitions into a terminal state
    (the whole team on its goals): no bootstrap there. A time-limit truncation is not terminal and does
    bootstrap. `gamma` is a float or a (B,) tensor (for n-step returns: gamma ** n).
    """
    b = _check_q(q, "q")
    if _check_q(next_q_target, "next_q_target") != b:
        raise ValueError(f"next_q_target has {next_q_target.shape[0]} rows, q has {b}")
    _check_actions(actions, b, "actions")
    _check_vec(rewards, b, "rewards")
    _check_vec(terminated, b, "terminated")
    with torch.no_grad():
        bootstrap = next_q_target.max(dim=1).values * (~terminated.bool()).to(q.dtype)
        target = rewards.to(q.dtype) + gamma * bootstrap
    q_taken = q.gather(1, actions.long()[:, None]).squeeze(1)
    return F.mse_loss(q_taken, target)


def hot_vectors(expert_actions: torch.Tensor, tau_h: float) -> torch.Tensor:
    """Table I: h(a*) = onehot(a*) - tau_h, with 0 < tau_h < 0.2 so that h(a*) . (1,...,1) = 1 - 5 tau_h > 0."""
    if not 0.0 < tau_h < 0.2:
        raise ValueError(f"tau_h must lie in (0, 0.2) (Table I), got {tau_h}")
    return F.one_hot(expert_actions.long(), N_ACTIONS).float() - tau_h


def hscl_loss(q: torch.Tensor, expert_actions: torch.Tensor, tau_h: float = 0.1, temperature: float = 0.1) -> torch.Tensor:
    """L2 (eq. 13) over a batch I of expert samples, averaged over anchors i in I.

    L_i = -1/|P(i)| sum_{p in P(i)} log( exp(cos(h(a*_i), q_p)/T) / sum_{j in I} exp(cos(h(a*_i), q_j)/T) )
    with q_j = Q(s_j, .) and P(i) = {p in I : a*_p = a*_i}.

    Readings of the ambiguous notation, and why:
    - P(i) includes i itself. In SupCon (eq. 12) the anchor is excluded because cos(z_i, z_i) = 1 is a
      trivial positive; here the anchor is the label's hot vector h(a*_i), not q_i, so q_i is an
      ordinary positive with nothing trivial about it.
    - The denominator runs over all of I, as eq. (13) writes it (not I minus {i}): same reason.
    Consequence: L_i depends only on the anchor's class c = a*_i, so L2 = sum_c (n_c / |I|) L_c where
    L_c is computed once per class present in the batch (exact, and 5 rows instead of |I|).
    The mean over anchors (not the sum of eq. 13) keeps the scale independent of the batch size.
    """
    b = _check_expert_batch(q, expert_actions, "hscl_loss")
    if not temperature > 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    prototypes = F.normalize(hot_vectors(torch.arange(N_ACTIONS, device=q.device), tau_h), dim=1)  # (5, 5)
    logits = prototypes @ F.normalize(q, dim=1).T / temperature  # (5, B): cos(h(c), q_j) / T
    log_prob = logits - torch.logsumexp(logits, dim=1, keepdim=True)
    positives = F.one_hot(expert_actions.long(), N_ACTIONS).T.to(q.dtype)  # (5, B): a*_j == c
    counts = positives.sum(dim=1)  # n_c
    per_class = -(positives * log_prob).sum(dim=1) / counts.clamp(min=1)  # L_c (0 for absent classes)
    return (counts * per_class).sum() / b


def margin_loss(q: torch.Tensor, expert_actions: torch.Tensor, margin: float) -> torch.Tensor:
    """Large-margin imitation (DQfD, Hester et al. 2018; not the paper's): mean over rows of
    max_a (q_a + margin [a != a*]) - q_{a*}. Zero once the expert's action leads every other by `margin`, so
    unlike HSCL, whose optimum q ~ h(a*) makes the other actions equal, it leaves their order to the DQN term."""
    _check_expert_batch(q, expert_actions, "margin_loss")
    if not margin > 0:
        raise ValueError(f"margin must be > 0, got {margin}")
    a = expert_actions.long()
    bonus = torch.full_like(q, margin).scatter(1, a[:, None], 0.0)
    return ((q + bonus).max(dim=1).values - q.gather(1, a[:, None]).squeeze(1)).mean()


def combined_loss(l1: torch.Tensor, l2: torch.Tensor, delta: float, phi: float) -> torch.Tensor:
    """Eq. (14): delta * L1 + phi * L2."""
    return delta * l1 + phi * l2


def expert_agreement(q: torch.Tensor, expert_actions: torch.Tensor) -> float:
    """Share of samples whose greedy action argmax Q equals the expert action (a training diagnostic)."""
    return float((q.argmax(dim=1) == expert_actions.long()).float().mean())
