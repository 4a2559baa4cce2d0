"""Reconstruction methods by name: each maps to a trainer class and its preset configs.

Methods register here so that ``nimbus-train --method NAME`` and the benchmark
harness treat them alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from nimbus.errors import NimbusError


@dataclass(frozen=True)
class Method:
    """A named reconstruction method.

    Attributes
    ----------
    name : str
    description : str
    trainer : callable returning the trainer class (imported lazily)
    preset : callable ``preset_name -> config``
    """

    name: str
    description: str
    trainer: Callable[[], type]
    preset: Callable[[str], object]


def _gs_trainer():
    from nimbus.train.trainer import GaussianTrainer

    return GaussianTrainer


def _gs_preset(name: str):
    from nimbus.train.config import preset

    return preset(name)


METHODS: dict[str, Method] = {
    "3dgs": Method("3dgs", "vanilla 3D Gaussian Splatting (Inria defaults)", _gs_trainer, _gs_preset),
}


def register(method: Method) -> None:
    METHODS[method.name] = method


def get_method(name: str) -> Method:
    try:
        return METHODS[name]
    except KeyError:
        raise NimbusError(f"unknown method {name!r}; choose one of: {', '.join(sorted(METHODS))}") from None


# NimbusGS and its paper variants register themselves; imported last because they
# build on Method and register above.
import nimbus.nimbusgs.methods  # noqa: E402,F401
