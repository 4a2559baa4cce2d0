"""Adaptive density control of 3DGS as a strategy (clone / split / prune / opacity reset).

In the spirit of gsplat's ``DefaultStrategy``: the settings are a frozen dataclass with
documented defaults (:class:`DefaultStrategy`), the running statistics are a plain dict
held by the caller (:meth:`DefaultStrategy.initialize_state`, checkpointed as is), and
one call per training step does the work (:meth:`DefaultStrategy.step_post_backward`).
It reads the per-Gaussian screen-space statistics of the rasterizer's ``meta`` and edits
the parameter tensors together with their Adam moments (:class:`~nimbus.train.params.GaussianParams`).

Two differences from gsplat, both to keep Inria's (and this project's earlier) arithmetic:

- ``params`` is a :class:`~nimbus.train.params.GaussianParams`, which carries its Adam
  optimiser, so there is no separate ``optimizers`` argument.
- :meth:`~DefaultStrategy.step_post_backward` is called after the optimiser step (Inria
  densifies the Gaussians the step has just updated), once per step, also in a step
  where no Gaussian was visible (``info`` empty: nothing is accumulated, the schedule
  still runs).  No ``step_pre_backward`` is needed: the rasterizer already retains the
  gradient of the screen-space means.

A method that reweights Gaussians' gradients (NimbusGS's GGS) passes the weights as
``info["grad2d_weight"]``; the strategy accumulates the weighted screen-space gradient.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from torch import Tensor

from nimbus.render.projection import quat_to_rotmat
from nimbus.train.config import TrainConfig
from nimbus.train.params import GaussianParams


@dataclasses.dataclass(frozen=True)
class DefaultStrategy:
    """Inria 3DGS densification settings (defaults: the Inria reference, :class:`~nimbus.train.config.TrainConfig`'s).

    Attributes
    ----------
    densify_from, densify_until, densify_interval : int
        Densify at steps ``densify_from < step <= densify_until`` that are multiples of ``densify_interval``.
    densify_grad_threshold : float
        Mean screen-space gradient norm (NDC units, Inria) above which a Gaussian is cloned or split.
    percent_dense : float
        Gaussians wider than this fraction of ``extent`` are split, smaller ones cloned.
    prune_opacity : float
        Gaussians less opaque than this are pruned at every densification step.
    prune_big_screen_px, prune_big_world : float
        After the first opacity reset, Gaussians wider than this on screen (pixels) or in the world
        (fraction of ``extent``, see ``prune_world_relative``) are pruned.
    prune_world_relative : bool
        Measure ``prune_big_world`` against ``max(extent, distance from center)`` (ours; False is Inria's).
    opacity_reset_interval : int
        Clamp every opacity to ``opacity_reset_value`` at the multiples of this step up to ``densify_until``.
    opacity_reset_value : float
    max_gaussians : int
        Cap on the Gaussian count; above it only the hottest Gaussians are densified.
    extent : float
        The scene extent lengths are fractions of (1 in the training frame).
    center : tuple of 3 float
        Mean camera centre, for ``prune_world_relative``.
    """

    densify_from: int = TrainConfig.densify_from
    densify_until: int = TrainConfig.densify_until
    densify_interval: int = TrainConfig.densify_interval
    densify_grad_threshold: float = TrainConfig.densify_grad_threshold
    percent_dense: float = TrainConfig.percent_dense
    prune_opacity: float = TrainConfig.prune_opacity
    prune_big_screen_px: float = TrainConfig.prune_big_screen_px
    prune_big_world: float = TrainConfig.prune_big_world
    prune_world_relative: bool = TrainConfig.prune_world_relative
    opacity_reset_interval: int = TrainConfig.opacity_reset_interval
    opacity_reset_value: float = TrainConfig.opacity_reset_value
    max_gaussians: int = TrainConfig.max_gaussians
    extent: float = 1.0
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def from_config(cls, config, extent: float = 1.0, center=None) -> "DefaultStrategy":
        """The strategy of a :class:`~nimbus.train.config.TrainConfig` (or a config with the same fields)."""
        names = [f.name for f in dataclasses.fields(cls) if f.name not in ("extent", "center")]
        c = (0.0, 0.0, 0.0) if center is None else tuple(float(x) for x in np.asarray(center, dtype=np.float64))
        return cls(**{n: getattr(config, n) for n in names}, extent=float(extent), center=c)

    # --- state ---------------------------------------------------------------------------
    @staticmethod
    def initialize_state() -> dict[str, Tensor]:
        """The running statistics, per Gaussian (sized on first use): gradient sum, view count, max radius."""
        return {"grad_accum": torch.zeros(0), "denom": torch.zeros(0), "max_radii": torch.zeros(0)}

    @staticmethod
    def _reset(state: dict, n: int, device) -> None:
        state["grad_accum"] = torch.zeros(n, device=device)
        state["denom"] = torch.zeros(n, device=device)
        state["max_radii"] = torch.zeros(n, device=device)

    # --- schedule ------------------------------------------------------------------------
    def is_densify_step(self, step: int) -> bool:
        return self.densify_from < step <= self.densify_until and step % self.densify_interval == 0

    def last_densify_step(self) -> int:
        """The last step :meth:`is_densify_step` accepts (0 when there is none)."""
        last = self.densify_until - self.densify_until % self.densify_interval
        return last if last > self.densify_from else 0

    def is_reset_step(self, step: int) -> bool:
        return step % self.opacity_reset_interval == 0 and step <= self.densify_until

    # --- the step ------------------------------------------------------------------------
    def step_post_backward(self, params: GaussianParams, state: dict, step: int, info: dict,
                           generator: torch.Generator) -> list[tuple[str, dict]]:
        """Accumulate this step's statistics (up to the last densification step), then densify / prune / reset
        opacities on the schedule.

        Parameters
        ----------
        params : GaussianParams
            Edited in place (tensors and Adam moments together).
        state : dict
            From :meth:`initialize_state`; updated in place.
        step : int
            The step just taken (1-based).
        info : dict
            Empty when the step saw no Gaussian; else ``means2d_grad`` [N, 2] (pixel units), ``radii`` [N],
            ``visible`` [N] bool, ``width``, ``height`` (the rendered image's size) and optionally
            ``grad2d_weight`` [N], a per-Gaussian weight of this view's gradient.
        generator : torch.Generator
            CPU generator of the split positions.

        Returns
        -------
        list of (str, dict)
            Events to log: ``("densify", {"gaussians", "cloned", "split", "pruned"})``, ``("opacity_reset", {})``.
        """
        # The statistics are read by the densification steps alone: after the last one nothing reads them (about
        # 2 ms a step at 200k Gaussians, half the run at the fast preset), and they stay zeros sized like the
        # model (a checkpoint's statistics must match its Gaussians).
        if step <= self.last_densify_step():
            if info.get("means2d_grad") is not None:
                self._accumulate(state, info)
        elif state["grad_accum"].shape[0] != len(params):
            self._reset(state, len(params), params["means"].device)
        events = []
        if self.is_densify_step(step):
            counts = self._densify_and_prune(params, state, step, generator)
            events.append(("densify", {"gaussians": len(params), **counts}))
        if self.is_reset_step(step):
            self._reset_opacity(params)
            events.append(("opacity_reset", {}))
        return events

    def _accumulate(self, state: dict, info: dict) -> None:
        """Add one view's |d loss / d mean2d| in NDC units (Inria) for the visible Gaussians."""
        radii = info["radii"]
        if state["grad_accum"].shape[0] != radii.shape[0]:
            self._reset(state, radii.shape[0], radii.device)
        visible = radii > 0
        g = info["means2d_grad"].detach()
        ndc = torch.stack([g[:, 0] * info["width"] * 0.5, g[:, 1] * info["height"] * 0.5], dim=-1).norm(dim=-1)
        # Masked in-place updates rather than boolean indexing (a gather and a scatter over the N
        # Gaussians per statistic and step): adding 0 to these sums and keeping the old maximum
        # where a Gaussian is not visible changes no bit.
        state["grad_accum"] += torch.where(visible, ndc, 0.0)
        weight = info.get("grad2d_weight")
        if weight is not None:
            # Adds the weighted gradient w * ndc as ndc + (w - 1) * ndc: the two roundings of the
            # statistic that the regression figures were made with (one add of w * ndc rounds differently).
            vis = info["visible"]
            state["grad_accum"][vis] += ((weight - 1.0) * ndc)[vis].to(state["grad_accum"])
        state["denom"] += visible
        state["max_radii"] = torch.where(visible, torch.maximum(state["max_radii"], radii.to(state["max_radii"])),
                                         state["max_radii"])

    def _densify_and_prune(self, params: GaussianParams, state: dict, step: int,
                           generator: torch.Generator) -> dict[str, int]:
        """One Inria densification step; returns counts of cloned, split and pruned Gaussians."""
        n = len(params)
        if state["grad_accum"].shape[0] != n:
            self._reset(state, n, params["means"].device)
        grads = torch.nan_to_num(state["grad_accum"] / state["denom"].clamp_min(1))
        grads[state["denom"] == 0] = 0
        with torch.no_grad():
            max_scale = torch.exp(params["log_scales"]).max(dim=1).values
            big = max_scale > self.percent_dense * self.extent
            hot = grads >= self.densify_grad_threshold
            room = max(self.max_gaussians - n, 0)
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
                noise = torch.randn(scales.shape, generator=generator, device="cpu").to(scales) * scales
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
            remove |= opac < self.prune_opacity
            if step > self.opacity_reset_interval:
                radii = torch.cat([state["max_radii"], torch.zeros(len(params) - n, device=state["max_radii"].device)])
                world = torch.exp(params["log_scales"].detach()).max(dim=1).values
                remove |= (radii > self.prune_big_screen_px) | (world > self.prune_big_world * self._world_reference(params))
            n_prune = int(remove.sum())
            params.keep(~remove)
        self._reset(state, len(params), params["means"].device)
        return {"cloned": n_clone, "split": n_split, "pruned": n_prune}

    def _world_reference(self, params: GaussianParams) -> Tensor | float:
        """The length ``prune_big_world`` is a fraction of: the extent, or per Gaussian max(extent, distance)."""
        if not self.prune_world_relative:
            return self.extent
        means = params["means"].detach()
        dist = (means - torch.as_tensor(np.asarray(self.center, dtype=np.float64)).to(means)).norm(dim=-1)
        return dist.clamp_min(self.extent)

    def _reset_opacity(self, params: GaussianParams) -> None:
        """Clamp every opacity to at most ``opacity_reset_value`` (Inria's periodic reset)."""
        cap = math.log(self.opacity_reset_value / (1 - self.opacity_reset_value))
        params.reset_state("opacity_logits", lambda t: torch.clamp_max(t, cap))
