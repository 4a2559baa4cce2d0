"""``restore-3dgs``: restore every training view in 2D, then train plain 3DGS on the restored views.

The two-stage baseline of the OR+3DGS / WeatherGS family: a single-image restorer
(:mod:`nimbus.restore`; classical and training-free by default, or a user's ONNX model) runs
once per training view at construction, the results are kept in memory, and
:class:`~nimbus.methods.gs3d.GaussianSplatting` trains on them unchanged.  The restorer sees
one view at a time, so what it removes or invents need not agree between views; that is the
weakness the baseline stands for.  Test views are never restored: they are only rendered.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass

import torch

from nimbus.data import Scene
from nimbus.methods.gs3d import GaussianSplatting
from nimbus.restore import Restorer, parse_restorer
from nimbus.train.config import PRESETS as GS_PRESETS
from nimbus.train.config import TrainConfig, lookup_preset
from nimbus.train.frame import SceneFrame


@dataclass(frozen=True)
class RestoreConfig3DGS(TrainConfig):
    """Every 3DGS field, plus ``restorer``: ``auto`` (default: chosen per view from what it shows),
    ``dcp``, ``particles``, ``dcp+particles``, ``none`` or ``onnx:PATH`` (:mod:`nimbus.restore`)."""

    restorer: str = "auto"

    def __post_init__(self) -> None:
        super().__post_init__()
        parse_restorer(self.restorer)


def preset(name: str) -> RestoreConfig3DGS:
    """The 3DGS preset ``name`` (``tiny``, ``fast``, ``paper``) with the default restorer."""
    return RestoreConfig3DGS(**dataclasses.asdict(lookup_preset(GS_PRESETS, name)))


class RestoreThen3DGS(GaussianSplatting):
    """3DGS on training views restored once by ``config.restorer`` (module docstring).

    Parameters are :class:`~nimbus.methods.gs3d.GaussianSplatting`'s; ``config`` is a
    :class:`RestoreConfig3DGS`.  A missing or unreadable ONNX model raises NimbusError here.
    """

    def __init__(self, scene: Scene, config: RestoreConfig3DGS, *, seed: int = 0,
                 device: torch.device | None = None, frame: SceneFrame | None = None) -> None:
        restorer = Restorer(config.restorer)  # fail on a bad model before any set-up work
        super().__init__(scene, config, seed=seed, device=device, frame=frame)
        self.restoration = restorer.describe()
        self.restored_steps: dict[str, list[str]] = {}
        for i, view in enumerate(self.train_views):
            restored, info = restorer(self.train_images[i].cpu().numpy())
            self.train_images[i] = torch.from_numpy(restored).to(self.device)
            self.restored_steps[view.name] = info["steps"]
        self._fresh = True

    def _summary(self) -> dict:
        counts = Counter("+".join(s) or "none" for s in self.restored_steps.values())
        return {**self.restoration, "views": dict(sorted(counts.items()))}

    def setup_events(self) -> list[tuple[str, dict]]:
        return [("restored", self._summary())] if self._fresh else []

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self._fresh = False

    def get_info(self) -> dict:
        return {"restore": {**self._summary(), "per_view": self.restored_steps}}
