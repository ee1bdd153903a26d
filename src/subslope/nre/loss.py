"""Neural ratio estimation loss (binary cross-entropy between joint and marginal pairs).

A classifier ``d(x, γ) = σ(f(γ, x))`` is trained to tell pairs drawn from the joint
``p(x, γ)`` (label 1) from pairs drawn from the product of marginals ``p(x)p(γ)``
(label 0). With balanced classes, the Bayes-optimal classifier satisfies
``d* = p(x,γ) / (p(x,γ) + p(x)p(γ))``, hence its logit is the likelihood-to-evidence
ratio ``f*(γ, x) = ln p(x|γ) − ln p(x)`` (Cranmer, Pavez & Louppe 2015, "Approximating
likelihood ratios with calibrated discriminative classifiers"; Hermans, Begy & Louppe
2020, "Likelihood-free MCMC with amortized approximate ratio estimators").

The objective minimised is

    L = ½ E_joint[−ln σ(f(γ, x))] + ½ E_marginal[−ln σ(−f(γ', x))]  (+ λ · B²)

estimated on a batch ``{(x_j, γ_j)}``: the positives are ``(x_j, γ_j)``, the negatives
``(x_j, γ_π(j))`` with γ permuted within the batch by a permutation without fixed points:

- ``negatives="roll"`` (default): ``π(j) = j − 1 mod B`` (``torch.roll`` by one, as lampe).
  The batches are already shuffled by the data loader, so this is an unbiased draw
  from ``p(x)p(γ)``, and it costs nothing.
- ``negatives="derangement"``: a fresh random cyclic derangement per batch (random
  order, then roll by one within it), drawn from the global torch RNG (or ``generator``).

Both terms use ``F.logsigmoid`` (``−ln σ(f) = softplus(−f)`` evaluated stably), so a
logit of ±1e4 gives a finite loss and finite gradients, where sigmoid-then-log
would give ``log(0) = −inf``.

Balanced NRE (Delaunoy et al. 2022, "Towards reliable simulation-based inference with
balanced neural ratio estimation") adds ``λ · B²`` with the balance
``B = E_joint[σ(f)] + E_marginal[σ(f)] − 1``; the optimal classifier has ``B = 0``, and
the penalty pushes the estimator towards conservative (wider) posteriors. ``λ = 0``
(default) is plain NRE; Delaunoy et al. recommend ``λ = 100``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["nre_loss", "negative_indices", "NRELoss"]

_NEGATIVES = ("roll", "derangement")


def negative_indices(
    batch: int, mode: str = "roll", *, generator: torch.Generator | None = None, device=None
) -> torch.Tensor:
    """Index ``π`` of the γ paired with each image in the negatives: ``γ_neg = γ[π]``.

    ``π(j) ≠ j`` for every ``j`` when ``batch ≥ 2``.
    """
    if mode not in _NEGATIVES:
        raise ValueError(f"negatives must be one of {list(_NEGATIVES)}, got {mode!r}")
    if batch < 2:
        raise ValueError(f"NRE needs a batch of at least 2 to form negatives, got {batch}")
    idx = torch.arange(batch, device=device)
    if mode == "roll":
        return torch.roll(idx, 1)
    order = torch.randperm(
        batch, generator=generator, device=generator.device if generator is not None else "cpu"
    ).to(device or "cpu")
    pi = torch.empty_like(order)
    pi[order] = torch.roll(order, 1)  # image order[k] gets γ of order[k-1]
    return pi


def nre_loss(
    log_r_pos: torch.Tensor, log_r_neg: torch.Tensor, *, lmbda: float = 0.0
) -> torch.Tensor:
    """Balanced BCE on logits of positive and negative pairs (plus the BNRE penalty if λ > 0)."""
    l1 = -F.logsigmoid(log_r_pos).mean()
    l0 = -F.logsigmoid(-log_r_neg).mean()
    loss = 0.5 * (l1 + l0)
    if lmbda:
        balance = torch.sigmoid(log_r_pos).mean() + torch.sigmoid(log_r_neg).mean() - 1.0
        loss = loss + lmbda * balance.square()
    return loss


class NRELoss(nn.Module):
    """NRE loss of an estimator ``f(γ, x) → ln r̂`` on a batch ``(γ, x)``.

    The estimator is called once with ``γ`` stacked as ``(2, B)`` (positives, then
    negatives), so a :class:`~subslope.nre.models.RatioEstimator` runs its trunk once.
    """

    def __init__(
        self,
        estimator: nn.Module,
        *,
        lmbda: float = 0.0,
        negatives: str = "roll",
        generator: torch.Generator | None = None,
    ):
        super().__init__()
        if negatives not in _NEGATIVES:
            raise ValueError(f"negatives must be one of {list(_NEGATIVES)}, got {negatives!r}")
        if not lmbda >= 0:
            raise ValueError(f"bnre lambda must be >= 0, got {lmbda!r}")
        self.estimator = estimator
        self.lmbda = float(lmbda)
        self.negatives = negatives
        self.generator = generator

    def forward(self, gamma: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        pi = negative_indices(
            gamma.shape[0], self.negatives, generator=self.generator, device=gamma.device
        )
        log_r = self.estimator(torch.stack((gamma, gamma[pi])), x)
        return nre_loss(log_r[0], log_r[1], lmbda=self.lmbda)
