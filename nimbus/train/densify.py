"""Adaptive density control of 3DGS (clone / split / prune / opacity reset), with optimiser surgery.

Kept apart from the renderer and the trainer (as gsplat's strategies are): it
reads the per-Gaussian screen-space statistics the renderer's ``meta`` gives and
edits the parameter tensors together with their Adam moments.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from nimbus.render.projection import quat_to_rotmat


class GaussianParams:
    """The trainable Gaussian tensors and their Adam optimiser, edited together.

    ``tensors`` maps parameter names (``means``, ``log_scales``, ``quats``,
    ``opacity_logits``, ``sh_dc``, ``sh_rest``, plus any per-Gaussian extras a
    method adds) to leaf tensors with ``requires_grad``; every tensor's first
    dimension is the Gaussian index.
    """

    def __init__(self, tensors: dict[str, Tensor], lrs: dict[str, float], eps: float) -> None:
        self.tensors = {k: v.detach().clone().requires_grad_(True) for k, v in tensors.items()}
        self.optimizer = torch.optim.Adam(
            [{"params": [self.tensors[k]], "lr": lrs[k], "name": k} for k in self.tensors], lr=0.0, eps=eps)

    def __len__(self) -> int:
        return self.tensors["means"].shape[0]

    def __getitem__(self, name: str) -> Tensor:
        return self.tensors[name]

    def set_lr(self, name: str, lr: float) -> None:
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                group["lr"] = lr

    def _replace(self, fn_param, fn_state) -> None:
        """Swap every tensor for ``fn_param(name, old)`` and its Adam moments for ``fn_state(name, moment)``."""
        for group in self.optimizer.param_groups:
            name = group["name"]
            old = group["params"][0]
            new = fn_param(name, old.detach()).requires_grad_(True)
            state = self.optimizer.state.pop(old, None)
            if state is not None:
                for key in ("exp_avg", "exp_avg_sq"):
                    state[key] = fn_state(name, state[key])
                self.optimizer.state[new] = state
            group["params"][0] = new
            self.tensors[name] = new

    def keep(self, mask: Tensor) -> None:
        """Keep only the Gaussians where ``mask`` [N] is True."""
        self._replace(lambda n, t: t[mask].clone(), lambda n, s: s[mask].clone())

    def append(self, new: dict[str, Tensor]) -> None:
        """Append Gaussians (a dict with every parameter name); their Adam moments start at zero."""
        self._replace(lambda n, t: torch.cat([t, new[n].to(t)]),
                      lambda n, s: torch.cat([s, torch.zeros_like(new[n], dtype=s.dtype)]))

    def reset_state(self, name: str, value_fn) -> None:
        """Set tensor ``name`` to ``value_fn(tensor)`` and zero its Adam moments (3DGS opacity reset)."""
        def param(n, t):
            return value_fn(t) if n == name else t

        def moment(n, s):
            return torch.zeros_like(s) if n == name else s

        self._replace(param, moment)

    def state_dict(self) -> dict:
        return {"tensors": {k: v.detach().clone() for k, v in self.tensors.items()},
                "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        names = [g["name"] for g in self.optimizer.param_groups]
        lrs = {g["name"]: g["lr"] for g in self.optimizer.param_groups}
        eps = self.optimizer.param_groups[0]["eps"]
        self.__init__({k: state["tensors"][k] for k in names}, lrs, eps)
        self.optimizer.load_state_dict(state["optimizer"])


class DensityController:
    """Inria 3DGS densification: accumulate screen-space gradient norms, then clone, split and prune.

    Parameters are read from a :class:`nimbus.train.config.TrainConfig`-like object
    (``densify_*``, ``percent_dense``, ``prune_*``, ``opacity_reset_*``, ``max_gaussians``).
    """

    def __init__(self, config, extent: float, generator: torch.Generator, center=None) -> None:
        self.cfg = config
        self.extent = extent
        # Mean camera centre, for ``prune_world_relative`` (None: the origin).
        self.center = torch.as_tensor(np.zeros(3) if center is None else np.asarray(center, dtype=np.float64))
        self.gen = generator
        self.grad_accum = torch.zeros(0)
        self.denom = torch.zeros(0)
        self.max_radii = torch.zeros(0)

    def reset_stats(self, n: int, device) -> None:
        self.grad_accum = torch.zeros(n, device=device)
        self.denom = torch.zeros(n, device=device)
        self.max_radii = torch.zeros(n, device=device)

    def accumulate(self, means2d_grad: Tensor, radii: Tensor, width: int, height: int) -> None:
        """Add one view's statistics: |d loss / d mean2d| in NDC units (Inria) for the visible Gaussians."""
        if self.grad_accum.shape[0] != radii.shape[0]:
            self.reset_stats(radii.shape[0], radii.device)
        visible = radii > 0
        g = means2d_grad.detach()
        ndc = torch.stack([g[:, 0] * width * 0.5, g[:, 1] * height * 0.5], dim=-1).norm(dim=-1)
        self.grad_accum[visible] += ndc[visible]
        self.denom[visible] += 1
        self.max_radii[visible] = torch.maximum(self.max_radii[visible], radii[visible].to(self.max_radii))

    def state_dict(self) -> dict:
        return {"grad_accum": self.grad_accum, "denom": self.denom, "max_radii": self.max_radii}

    def load_state_dict(self, state: dict) -> None:
        self.grad_accum, self.denom, self.max_radii = state["grad_accum"], state["denom"], state["max_radii"]

    def is_densify_step(self, it: int) -> bool:
        c = self.cfg
        return c.densify_from < it <= c.densify_until and it % c.densify_interval == 0

    def is_reset_step(self, it: int) -> bool:
        c = self.cfg
        return it % c.opacity_reset_interval == 0 and it <= c.densify_until

    def densify_and_prune(self, params: GaussianParams, it: int) -> dict[str, int]:
        """One Inria densification step; returns counts of cloned, split and pruned Gaussians."""
        c = self.cfg
        n = len(params)
        if self.grad_accum.shape[0] != n:
            self.reset_stats(n, params["means"].device)
        grads = torch.nan_to_num(self.grad_accum / self.denom.clamp_min(1))
        grads[self.denom == 0] = 0
        with torch.no_grad():
            max_scale = torch.exp(params["log_scales"]).max(dim=1).values
            big = max_scale > c.percent_dense * self.extent
            hot = grads >= c.densify_grad_threshold
            room = max(c.max_gaussians - n, 0)
            clone = hot & ~big
            split = hot & big
            if int(clone.sum()) + int(split.sum()) > room:  # respect the cap: keep the hottest
                order = torch.argsort(grads, descending=True)
                allowed = torch.zeros_like(hot)
                allowed[order[: room // 2]] = True
                clone &= allowed
                split &= allowed
            n_clone, n_split = int(clone.sum()), int(split.sum())
            new = {k: v.detach()[clone] for k, v in params.tensors.items()}
            if n_split:
                idx = split.nonzero().squeeze(1).repeat(2)
                scales = torch.exp(params["log_scales"].detach()[idx])
                rot = quat_to_rotmat(params["quats"].detach()[idx])
                noise = torch.randn(scales.shape, generator=self.gen, device="cpu").to(scales) * scales
                split_new = {k: v.detach()[idx] for k, v in params.tensors.items()}
                split_new["means"] = split_new["means"] + torch.einsum("nij,nj->ni", rot, noise)
                split_new["log_scales"] = torch.log(scales / 1.6)
                new = {k: torch.cat([new[k], split_new[k]]) for k in new}
            if n_clone or n_split:
                params.append(new)
            # The split originals go; so do transparent and (after the first reset) oversized Gaussians.
            remove = torch.cat([torch.zeros(n, dtype=torch.bool, device=split.device) | split,
                                torch.zeros(len(params) - n, dtype=torch.bool, device=split.device)])
            opac = torch.sigmoid(params["opacity_logits"].detach())
            remove |= opac < c.prune_opacity
            if it > c.opacity_reset_interval:
                radii = torch.cat([self.max_radii, torch.zeros(len(params) - n, device=self.max_radii.device)])
                world = torch.exp(params["log_scales"].detach()).max(dim=1).values
                remove |= (radii > c.prune_big_screen_px) | (world > c.prune_big_world * self._world_reference(params))
            n_prune = int(remove.sum())
            params.keep(~remove)
        self.reset_stats(len(params), params["means"].device)
        return {"cloned": n_clone, "split": n_split, "pruned": n_prune}

    def _world_reference(self, params: GaussianParams) -> Tensor | float:
        """The length ``prune_big_world`` is a fraction of: the extent, or per Gaussian max(extent, distance)."""
        if not getattr(self.cfg, "prune_world_relative", False):
            return self.extent
        means = params["means"].detach()
        dist = (means - self.center.to(means)).norm(dim=-1)
        return dist.clamp_min(self.extent)

    def reset_opacity(self, params: GaussianParams) -> None:
        """Clamp every opacity to at most ``opacity_reset_value`` (Inria's periodic reset)."""
        cap = math.log(self.cfg.opacity_reset_value / (1 - self.cfg.opacity_reset_value))
        params.reset_state("opacity_logits", lambda t: torch.clamp_max(t, cap))
