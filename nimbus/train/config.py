"""Training configuration for vanilla 3DGS: the Inria defaults as a frozen dataclass, with named presets.

The Inria schedule is written for 30k iterations; the short presets (``tiny``,
``fast``) use fewer, later densification steps (see :data:`PRESETS`).  Overriding
``iterations`` rescales a preset's whole schedule.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from nimbus.errors import NimbusError



@dataclass(frozen=True)
class TrainConfig:
    """3DGS training configuration (defaults: the Inria reference, 30k iterations).

    Learning rates are per Adam parameter group; ``lr_means_*`` are multiplied by
    the scene extent and decay log-linearly from init to final over the run.

    ``train_downscale`` (integer >= 1, default 1) trains on the training views shrunk by
    that factor (area averaging, cameras scaled to match) while the test views are still
    rendered and scored at full size: fewer pixels per step for a blurrier model (the
    image-scale knob of ``nimbus-bench tradeoff``).  Pixel-unit settings (``prune_big_screen_px``,
    NimbusGS's ``dcp_patch`` and ``ggs_r0``) then count pixels of the shrunk images.

    ``prune_world_relative`` (ours; False is Inria's rule): Inria prunes every Gaussian
    wider than ``prune_big_world * extent`` in world units, where the extent is the radius
    of the camera centres.  Far content (hills, the end of a street) drawn at a few
    pixels per Gaussian is many times that wide at low resolution, and a forward-facing
    capture has a tiny extent, so that rule deletes the background every densification
    step.  With True the threshold is ``prune_big_world * max(extent, distance from the
    mean camera centre)``: unchanged inside the camera region, an angular limit beyond.
    """

    iterations: int = 30_000
    # learning rates (Inria)
    lr_means_init: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    adam_eps: float = 1e-15
    # loss
    lambda_dssim: float = 0.2
    # spherical harmonics
    sh_degree: int = 3
    sh_degree_interval: int = 1000
    # densification (Inria)
    densify_from: int = 500
    densify_until: int = 15_000
    densify_interval: int = 100
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    prune_big_screen_px: float = 20.0
    prune_big_world: float = 0.1
    # ours, off in the Inria defaults: measure prune_big_world against max(extent, the
    # Gaussian's distance from the mean camera centre), i.e. as an angle for far content
    prune_world_relative: bool = False
    opacity_reset_interval: int = 3000
    opacity_reset_value: float = 0.01
    max_gaussians: int = 3_000_000
    # initialisation
    init_opacity: float = 0.1
    init_random_points: int = 10_000
    # training images: shrunk by this integer factor (test views stay full size)
    train_downscale: int = 1
    # rendering
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    random_background: bool = False
    backend: str = "auto"
    tile_size: int = 16
    near_plane: float = 0.01
    # bookkeeping
    log_interval: int = 10
    checkpoint_interval: int = 1000
    test_interval: int = 0

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise NimbusError(f"iterations must be >= 1, got {self.iterations}")
        if not 0 <= self.sh_degree <= 3:
            raise NimbusError(f"sh_degree must be in 0..3, got {self.sh_degree}")
        if not 0.0 <= self.lambda_dssim <= 1.0:
            raise NimbusError(f"lambda_dssim must be in [0, 1], got {self.lambda_dssim}")
        if self.backend not in ("auto", "torch", "cpp", "gsplat"):
            raise NimbusError(f"backend must be auto, torch, cpp or gsplat, got {self.backend!r}")
        for name in ("densify_interval", "sh_degree_interval", "opacity_reset_interval", "tile_size",
                     "train_downscale"):
            if getattr(self, name) < 1:
                raise NimbusError(f"{name} must be >= 1, got {getattr(self, name)}")

    def rescaled(self, iterations: int) -> "TrainConfig":
        """This config with every schedule step stretched or shrunk by ``iterations / self.iterations``."""
        ratio = iterations / self.iterations
        return dataclasses.replace(self, iterations=iterations, **{
            name: max(int(round(getattr(self, name) * ratio)), 1) for name in SCHEDULE_FIELDS})

    def with_overrides(self, overrides: dict[str, str]) -> "TrainConfig":
        """Apply ``--set key=value`` overrides, parsing each value as the field's type.

        Changing ``iterations`` alone rescales the whole schedule (densification,
        resets, SH steps) so a longer or shorter run keeps the preset's shape.
        """
        config = self
        if "iterations" in overrides and not SCHEDULE_FIELDS & overrides.keys():
            config = config.rescaled(int(_parse_like(1, overrides["iterations"], "iterations")))
        return apply_overrides(config, overrides)


SCHEDULE_FIELDS = frozenset({"densify_from", "densify_until", "densify_interval", "opacity_reset_interval",
                             "sh_degree_interval", "checkpoint_interval"})

def apply_overrides(config, overrides: dict[str, str]):
    """Return ``config`` (a frozen dataclass) with string overrides parsed to the fields' types."""
    fields = {f.name: f for f in dataclasses.fields(config)}
    changes = {}
    for key, raw in overrides.items():
        if key not in fields:
            close = ", ".join(sorted(n for n in fields if key.split("_")[0] in n)[:8]) or ", ".join(sorted(fields)[:12])
            raise NimbusError(f"unknown setting {key!r}; known settings include: {close}")
        current = getattr(config, key)
        changes[key] = _parse_like(current, raw, key)
    return dataclasses.replace(config, **changes)


def _parse_like(current, raw: str, key: str):
    try:
        if isinstance(current, bool):
            if raw.lower() in ("1", "true", "yes", "on"):
                return True
            if raw.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(raw)
        if isinstance(current, int):
            return int(float(raw)) if float(raw).is_integer() else int(raw)
        if isinstance(current, float):
            return float(raw)
        if isinstance(current, tuple):
            parts = [p for p in raw.replace("(", "").replace(")", "").split(",") if p.strip()]
            return tuple(type(current[0])(p) for p in parts) if current else tuple(parts)
        return raw
    except ValueError:
        raise NimbusError(f"setting {key}={raw!r}: expected a value like {current!r}") from None


def parse_set_args(items: list[str] | None) -> dict[str, str]:
    """Parse ``["key=value", ...]`` from ``--set`` flags."""
    out: dict[str, str] = {}
    for item in items or []:
        if "=" not in item:
            raise NimbusError(f"--set expects key=value, got {item!r}")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


# Short runs cannot afford the Inria schedule's ~145 densification steps: each step can
# double a region's Gaussians, and early steps fire on the gradients of a still
# unfitted model.  The short presets start densifying once the fit has settled a
# little (~15 % of the run), densify every ~1/20 of the run until half-way, and cap
# the count so a CPU run stays affordable.  ``fast`` measures the world-size prune
# relative to distance (``prune_world_relative``): with Inria's rule the 3DGS fast run on
# the small built-in scenes lost 1.7 dB (garden) to deleted background Gaussians.
PRESETS: dict[str, TrainConfig] = {
    # CI: seconds on the tiny built-in scenes.
    "tiny": TrainConfig(
        iterations=300, sh_degree=1, sh_degree_interval=100, densify_from=60, densify_until=180,
        densify_interval=30, opacity_reset_interval=10**9, max_gaussians=20_000, checkpoint_interval=100,
    ),
    # Minutes on the CPU for the small built-in scenes.
    "fast": TrainConfig(
        iterations=3000, sh_degree=3, sh_degree_interval=300, densify_from=300, densify_until=1500,
        densify_interval=100, opacity_reset_interval=1000, max_gaussians=200_000, checkpoint_interval=500,
        prune_world_relative=True,
    ),
    # The paper's 30k-iteration schedule.
    "paper": TrainConfig(),
}


def lookup_preset(presets: dict, name: str):
    """``presets[name]``; an unknown name raises :class:`NimbusError` listing the known ones."""
    try:
        return presets[name]
    except KeyError:
        raise NimbusError(f"unknown preset {name!r}; choose one of {', '.join(presets)}") from None


def preset(name: str) -> TrainConfig:
    """A named 3DGS preset (``tiny``, ``fast``, ``paper``)."""
    return lookup_preset(PRESETS, name)
