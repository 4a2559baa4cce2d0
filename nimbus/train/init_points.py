"""The points a run starts from when the scene has no sparse points, and the record of that choice.

A scene with sparse points (COLMAP SfM, a built-in scene) starts from them, as 3DGS does, and nothing
here happens.  A posed capture without points (transforms.json, a COLMAP model with an empty
``points3D``) gets, in this order:

1. ``triangulated``: points triangulated from its training views with the poses fixed
   (:func:`nimbus.data.triangulate.triangulate_posed`, cached by content in the user cache, never in
   the scene folder), when there are at least :data:`~nimbus.data.triangulate.MIN_TRIANGULATED_POINTS`.  They become the
   scene's sparse points for the run, so what methods read from them (NimbusGS's haze evidence,
   the medium's initial estimate) sees measured surfaces.  With ``init_densify`` > 0 that many
   pixels of the training views are added to them (:mod:`nimbus.data.densify`): at the depth of
   nearby triangulated points, or on the backdrop at a far depth (a guess, which those methods
   then read as well).
2. ``focus`` or ``forward``: otherwise ``init_random_points`` random points placed from the cameras
   (:mod:`nimbus.data.camera_focus`) by the method's :func:`~nimbus.render.gaussians.init_from_scene`.
   They are not added to the scene: they are not measurements.

Triangulation is skipped (straight to 2) when the config's ``init_triangulate`` is off, when there
are fewer than two training views, or when the images are smaller than
:data:`~nimbus.data.triangulate.MIN_TRIANGULATION_SIDE_PX`.
The choice is said in one line on stderr and recorded (:attr:`InitPoints.record`, ``init_points`` in
``results.json`` and the training log).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from nimbus.data import Scene
from nimbus.data.densify import DensifyConfig, densify_points
from nimbus.data.triangulate import MIN_TRIANGULATED_POINTS, triangulate_posed, triangulation_skip_reason
from nimbus.errors import NimbusError
from nimbus.render.gaussians import GaussianInitConfig, random_init_plan

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InitPoints:
    """What a run starts from.

    Attributes
    ----------
    scene : Scene
        The scene to train on: as given, or with the triangulated points as its sparse points.
    record : dict
        ``source`` (``"scene"``, ``"triangulated"``, ``"focus"`` or ``"forward"``), ``points`` (the
        count), and for a points-less scene ``triangulation`` (its info, or why it was skipped),
        ``densify`` (:func:`~nimbus.data.densify.densify_points`'s info, when it was used) and,
        for random points, ``random`` (where: :meth:`~nimbus.data.camera_focus.RandomInitPlan.to_dict`).
    line : str or None
        The one-line notice (None when the scene had points).
    """

    scene: Scene
    record: dict
    line: str | None


def _home(path: str) -> str:
    """``path`` with the home folder written ``~`` (shorter notices)."""
    home = str(Path.home())
    return "~" + path[len(home):] if path.startswith(home + os.sep) else path


def choose_init_points(scene: Scene, config, seed: int = 0, cache_dir: str | os.PathLike | None = None,
                       log_step: Callable[[str], None] | None = None) -> InitPoints:
    """The points a run of ``config`` (a :class:`~nimbus.train.config.TrainConfig`) starts from (module docstring).

    For a scene without points the choice is logged (one warning-level line, which reaches stderr
    without any logging set-up) and returned in :attr:`InitPoints.line`.

    Parameters
    ----------
    scene : Scene
        As loaded (world coordinates).
    config : TrainConfig
        ``init_triangulate``, ``init_densify`` and ``init_random_points`` are read.
    seed : int
        The run's seed (random points).
    cache_dir : path, optional
        Triangulation cache (default :func:`nimbus.data.triangulate.default_cache_dir`).
    log_step : callable, optional
        Receives the triangulation's progress lines.
    """
    if len(scene.points):
        return InitPoints(scene, {"source": "scene", "points": int(len(scene.points))}, None)
    views = scene.train_views or list(scene.views)
    tri, why = None, None
    if not getattr(config, "init_triangulate", True):
        why = "triangulation is off (init_triangulate=false)"
    else:
        why = triangulation_skip_reason(views)
    if why is None:
        tri = triangulate_posed(views, cache_dir=cache_dir, log=log_step)
        tri_record = {k: v for k, v in tri.info.items() if k != "key"}
        if len(tri.points) >= MIN_TRIANGULATED_POINTS:
            where = (f"reused the cached triangulation {_home(tri_record['cache'])}" if tri_record["reused"] else
                     f"cached in {_home(tri_record['cache'])}; the scene folder is not written")
            line = (f"init: the scene has no sparse points: triangulated {len(tri.points)} points from "
                    f"{len(views)} posed training views with the poses fixed ({where})")
            points, colors, record = tri.points, tri.colors, {"source": "triangulated", "points": int(len(tri.points)),
                                                              "triangulation": tri_record}
            n_dense = int(getattr(config, "init_densify", 0))
            if n_dense > 0:
                points, colors, dense = densify_points(views, tri.points, tri.colors,
                                                       DensifyConfig(samples=n_dense, seed=seed,
                                                                     sweep=bool(getattr(config, "init_sweep", True))))
                record = {**record, "points": int(len(points)), "densify": dense}
                line += (f"; densified with {dense['samples']} pixels of the training views ({dense['swept']} at a "
                         f"depth measured by a plane sweep, {dense['near']} at the depth of nearby points, "
                         f"{dense['far']} on the backdrop; init_densify={n_dense})")
            log.warning("%s", line)
            return InitPoints(dataclasses.replace(scene, points=points, colors=colors), record, line)
        why = (f"triangulation found {len(tri.points)} points in {len(views)} posed training views "
               f"(< {MIN_TRIANGULATED_POINTS})")
    n_random = int(config.init_random_points)
    if n_random < 1:
        raise NimbusError(f"the scene has no sparse points and {why}, so training starts from random points, but "
                          "init_random_points is 0; set it to a positive count (--set init_random_points=10000)")
    plan = random_init_plan(scene, GaussianInitConfig(random_points=n_random, seed=seed))
    record = {"source": plan.kind, "points": n_random, "random": plan.to_dict(),
              "triangulation": tri_record if tri is not None else {"skipped": why}}
    line = f"init: the scene has no sparse points; {why}: starting from {n_random} random points in {plan.describe()}"
    log.warning("%s", line)
    return InitPoints(scene, record, line)


__all__ = ["InitPoints", "choose_init_points"]
