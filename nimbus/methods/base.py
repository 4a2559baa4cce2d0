"""The method protocol: what :class:`~nimbus.train.runner.Runner` asks of a reconstruction method.

In the spirit of nerfbaselines: a method is built from a scene and a config, trains one
step at a time, renders a camera, and saves and restores its state; the runner owns
everything else (run folder, config record, checkpoints and resume, log, progress bar,
guards, test renders and scores, PLY, ``results.json``).

Conventions
-----------
- The scene a method receives is in the training frame (:class:`~nimbus.train.frame.SceneFrame`:
  centred on the cameras, extent 1); ``frame`` says how it maps to the world, for a method
  that reports lengths in world units.  Cameras given to :meth:`Method.render` are of that
  frame, and :meth:`Method.gaussians` is in it (the runner converts to world coordinates).
- Images are float32 torch tensors ``[H, W, 3]`` in [0, 1] on the method's device.
- A method seeds its own random generators from ``seed`` (and may seed torch's global one);
  the runner checkpoints torch's global RNG state only through the method's state dict.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch

from nimbus.data import Camera
from nimbus.render.gaussians import Gaussians


class TrainingDiverged(Exception):
    """Raised by :meth:`Method.train_iteration` when the loss or the gradients are not finite.

    The method must raise it before it changes any parameter, so its state is still the last
    good one: the runner saves that state as ``checkpoint_last_good.pt`` and stops with a
    :class:`~nimbus.errors.NimbusError`.

    Attributes
    ----------
    what : str
        ``"loss"`` or ``"gradients"``.
    value : float or None
        The loss value (for ``"loss"``).
    """

    def __init__(self, what: str, value: float | None = None) -> None:
        super().__init__(f"non-finite {what}")
        self.what = what
        self.value = value


@runtime_checkable
class Method(Protocol):
    """A reconstruction method.

    Constructed as ``cls(scene, config, seed=..., device=..., frame=...)``: ``scene`` in the
    training frame (its ``train_views`` are trained on), ``config`` the method's config
    (a frozen dataclass from its registry presets), ``seed`` an int, ``device`` a
    :class:`torch.device` (None: the method picks), ``frame`` the scene's
    :class:`~nimbus.train.frame.SceneFrame`.
    """

    #: The training views, as trained on (e.g. downscaled); their cameras are valid for :meth:`render`.
    train_views: list

    def train_iteration(self, step: int) -> dict:
        """Train one step (``step`` counts from 1).

        Returns a dict with ``loss`` (float), ``psnr`` (float, dB: the training view against what the
        loss compared it with), ``visible`` (bool: whether anything in the view depended on the model)
        and ``events`` (list of ``(kind, info)`` to log, in order).  Raises :class:`TrainingDiverged`.
        """

    def render(self, camera: Camera, *, view_index: int | None = None) -> dict:
        """Render ``camera`` (of the training frame).

        Returns at least ``rgb`` [H, W, 3] (what is scored), ``depth`` [H, W] and ``alpha`` [H, W], and
        ``meta`` with a bool ``visible`` per primitive where that applies (a render that shows nothing of
        the model is not scored).  ``view_index`` says that ``camera`` is training view ``view_index``'s
        (``train_views[view_index].camera``): a method with a per-view model adds its extras for that
        view (NimbusGS: ``transmission``, ``airlight``, ``residual``, ``degraded``); others ignore it.
        """

    def state_dict(self) -> dict:
        """Everything :meth:`load_state_dict` restores: tensors and plain values only
        (:func:`~nimbus.train.checkpoint.check_plain`), keys other than the runner's own
        (``iteration``, ``train_time``, ``frame``, ``visible_steps``, ``mid_step``)."""

    def load_state_dict(self, state: dict) -> None:
        """Restore a :meth:`state_dict`; ``state["iteration"]`` is the step it was saved after.

        Raise KeyError / TypeError / ValueError (the runner reports them as a checkpoint that does not fit).
        """

    def get_info(self) -> dict:
        """JSON-able method-specific results, added to ``results.json`` (``{}`` when there are none)."""

    def gaussians(self) -> Gaussians:
        """The model as Gaussians in the training frame (written as ``point_cloud.ply``)."""

    def param_groups(self) -> list[dict]:
        """Every optimised tensor, as optimiser param groups (``params`` and ``name``): the runner checks
        they are finite at the end of training."""

    @property
    def num_gaussians(self) -> int:
        """How many primitives the model has (0: everything was pruned, training stops)."""

    def setup_events(self) -> list[tuple[str, dict]]:
        """Events of the set-up to log once, before the first step (empty after :meth:`load_state_dict`)."""

    def write_outputs(self, out_dir) -> None:
        """Write method-specific outputs into the run folder (before the test renders)."""


def default_device() -> torch.device:
    return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
