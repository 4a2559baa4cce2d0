"""Training configuration for vanilla 3DGS: the Inria defaults as a frozen dataclass, with named presets.

The Inria schedule is written for 30k iterations; the short presets (``tiny``,
``fast``) use fewer, later densification steps (see :data:`PRESETS`).  Overriding
``iterations`` rescales a preset's whole schedule.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

from nimbus.config_validation import INT_MAX, Limit, at_least, between, fraction, one_of, positive, validate
from nimbus.errors import NimbusError
from nimbus.render.backends import BACKENDS


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

    Lengths are in units of the scene extent: the trainer works in a frame centred on the
    mean camera centre with extent 1 (:class:`nimbus.train.frame.SceneFrame`, as gsplat and
    nerfstudio normalise), so ``near_plane`` 0.01 is 1 % of the extent whatever the units of
    the reconstruction (Inria's 0.01 is in COLMAP units, which are arbitrary).

    ``prune_world_relative`` (ours; False is Inria's rule): Inria prunes every Gaussian
    wider than ``prune_big_world * extent`` in world units, where the extent is the radius
    of the camera centres.  Far content (hills, the end of a street) drawn at a few
    pixels per Gaussian is many times that wide at low resolution, and a forward-facing
    capture has a tiny extent, so that rule deletes the background every densification
    step.  With True the threshold is ``prune_big_world * max(extent, distance from the
    mean camera centre)``: unchanged inside the camera region, an angular limit beyond.

    Initialisation of a scene without sparse points (ours; :mod:`nimbus.train.init_points`): with
    ``init_triangulate`` (default True) points triangulated from the posed training views with
    pycolmap (cached in ``$NIMBUS_CACHE/triangulated``); where that finds too few,
    ``init_random_points`` random points about the cameras' focus, or in their view frusta for a
    forward-facing capture (:mod:`nimbus.data.camera_focus`).  A scene with points starts from them.
    Triangulated points are densified with ``init_densify`` pixels of the training views, each at
    the depth a plane sweep over its neighbouring views measures (``init_sweep``,
    :mod:`nimbus.data.sweep`), else at the depth of the points projected near it or, where none is,
    at a far depth, so the backdrop SIFT found nothing on gets Gaussians to grow from
    (:mod:`nimbus.data.densify`; 0 turns it off).
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
    # a scene without sparse points: triangulate its posed training views (cached) before random points
    init_triangulate: bool = True
    # triangulated points: add this many pixels of the training views (the backdrop included), 0: off
    init_densify: int = 30_000
    # densified pixels: their depth measured by a plane sweep over neighbouring views where it can be
    init_sweep: bool = True
    # training images: shrunk by this integer factor (test views stay full size)
    train_downscale: int = 1
    # rendering
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    random_background: bool = False
    backend: str = "auto"
    tile_size: int = 16
    near_plane: float = 0.01  # in units of the scene extent (see above)
    # bookkeeping
    log_interval: int = 10
    checkpoint_interval: int = 1000
    test_interval: int = 0

    #: The accepted values of each field (see :mod:`nimbus.config_validation`).
    LIMITS: ClassVar[dict[str, Limit]] = {
        "iterations": at_least(1),
        # learning rates: > 0 where the schedule takes their log, >= 0 (0 freezes the group) elsewhere
        "lr_means_init": positive(note="decays log-linearly"), "lr_means_final": positive(note="decays log-linearly"),
        "lr_sh_dc": at_least(0), "lr_sh_rest": at_least(0), "lr_opacity": at_least(0), "lr_scales": at_least(0),
        "lr_quats": at_least(0), "adam_eps": positive(),
        "lambda_dssim": fraction(),
        "sh_degree": between(0, 3), "sh_degree_interval": at_least(1),
        "densify_from": at_least(0), "densify_until": at_least(0), "densify_interval": at_least(1),
        "densify_grad_threshold": at_least(0), "percent_dense": at_least(0),
        "prune_opacity": fraction(), "prune_big_screen_px": at_least(0), "prune_big_world": at_least(0),
        # stored through the logit: 0 and 1 are +-inf
        "opacity_reset_interval": at_least(1), "opacity_reset_value": between(0, 1, lo_open=True, hi_open=True),
        "max_gaussians": at_least(1),
        "init_opacity": between(0, 1, lo_open=True, hi_open=True), "init_random_points": at_least(0),
        "init_densify": at_least(0, note="0: off"),
        "train_downscale": at_least(1),
        "background": fraction(note="R, G, B"),
        "backend": one_of(*BACKENDS),
        "tile_size": at_least(1),
        "near_plane": positive(),
        "log_interval": at_least(1), "checkpoint_interval": at_least(1), "test_interval": at_least(0, note="0: off"),
    }

    def __post_init__(self) -> None:
        validate(self)

    def rescaled(self, iterations: int) -> "TrainConfig":
        """This config with every schedule step stretched or shrunk by ``iterations / self.iterations``."""
        ratio = iterations / self.iterations
        return dataclasses.replace(self, iterations=iterations, **{
            name: rescale_step(getattr(self, name), ratio) for name in SCHEDULE_FIELDS})

    def with_changes(self, changes: dict) -> "TrainConfig":
        """This config with ``changes`` (field -> value) applied, as ``--set`` does (:mod:`nimbus.config_set`).

        Changing ``iterations`` alone rescales the whole schedule (densification, resets, SH
        steps) so a longer or shorter run keeps the preset's shape.
        """
        config = self
        if "iterations" in changes and not SCHEDULE_FIELDS & changes.keys():
            config = config.rescaled(changes["iterations"])
        return dataclasses.replace(config, **changes)


SCHEDULE_FIELDS = frozenset({"densify_from", "densify_until", "densify_interval", "opacity_reset_interval",
                             "sh_degree_interval", "checkpoint_interval"})


def rescale_step(step: int, ratio: float) -> int:
    """A schedule step (an interval, a start) times ``ratio``, kept within 1..INT_MAX.

    A preset's "never" (``opacity_reset_interval=10**9``) stretched by a longer run stays "never".
    """
    return min(max(int(round(step * ratio)), 1), INT_MAX)


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
