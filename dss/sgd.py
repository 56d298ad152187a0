"""Stochastic gradient descent with (Nesterov) momentum, without ``torch.optim``.

``torch.optim.Optimizer`` imports ``torch._dynamo`` on construction (about 2 s of a 20K-point
denoising job's wall time on 2 cores, more than its outlier removal, normals and noise
estimate together). The optimiser the paper uses is a few tensor operations, so it lives here
with the interface :class:`dss.optimize.MultiViewOptimizer` needs (``param_groups`` with
``lr``, ``state``, ``zero_grad``, ``step``). It computes what ``torch.optim.SGD`` computes with
``dampening=0`` and ``weight_decay=0`` (tests/test_optimize.py compares the two):

    b <- g                      (first step)      b <- momentum * b + g   (later steps)
    d <- g + momentum * b       (nesterov)        d <- b                  (otherwise)
    p <- p - lr * d
"""

from __future__ import annotations

import torch


class SGD:
    """SGD on a list of tensors. ``state`` maps a parameter to ``{"momentum_buffer": b}``;
    clearing it restarts the momentum (as ``torch.optim.SGD``'s ``state.clear()`` does)."""

    def __init__(self, params, lr: float, momentum: float = 0.0, nesterov: bool = False):
        if lr < 0 or momentum < 0:
            raise ValueError(f"lr and momentum must be >= 0, got lr={lr}, momentum={momentum}")
        if nesterov and momentum <= 0:
            raise ValueError("Nesterov momentum requires momentum > 0")
        self.param_groups = [{"params": list(params), "lr": float(lr), "momentum": float(momentum),
                              "nesterov": bool(nesterov)}]
        self.state: dict = {}

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                if set_to_none:
                    p.grad = None
                else:
                    p.grad.detach_().zero_()

    @torch.no_grad()
    def step(self) -> None:
        for group in self.param_groups:
            mu, lr = group["momentum"], group["lr"]
            for p in group["params"]:
                g = p.grad
                if g is None:
                    continue
                if mu > 0:
                    st = self.state.setdefault(p, {})
                    b = st.get("momentum_buffer")
                    if b is None:
                        b = st["momentum_buffer"] = g.detach().clone()
                    else:
                        b.mul_(mu).add_(g)
                    g = g.add(b, alpha=mu) if group["nesterov"] else b
                p.add_(g, alpha=-lr)
