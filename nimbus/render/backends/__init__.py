"""Rasterizer backends: one module per backend, every one registered by name in :data:`REGISTRY`.

Each backend module defines ``BACKEND``, a :class:`~nimbus.render.backends.base.Backend`
with one call signature and one ``meta`` shape (see there); :func:`nimbus.render.rasterize`
checks the arguments and dispatches through :func:`resolve`.  Adding a backend is one new
module and one line in :data:`REGISTRY`.  Modules are imported on first use, so a backend
whose optional dependencies are missing costs the others nothing.

(The modules ``torch`` and ``gsplat`` here share their names with the packages they wrap:
imports are absolute, so ``import torch`` anywhere still gets the real package, but this
package's attribute ``torch`` is the backend module once it is loaded; hence no module-level
``import torch`` in this file.)
"""

from __future__ import annotations

import importlib

from nimbus.errors import NimbusError
from nimbus.render.backends.base import Backend

#: Backend name -> ``"module:attribute"`` of its :class:`Backend`.
REGISTRY: dict[str, str] = {
    "torch": "nimbus.render.backends.torch:BACKEND",
    "cpp": "nimbus.render.backends.cpp:BACKEND",
    "gsplat": "nimbus.render.backends.gsplat:BACKEND",
}

#: What ``rasterize(backend=...)`` and the training config's ``backend`` accept.
BACKENDS = ("auto", *REGISTRY)


def get(name: str) -> Backend:
    """The registered backend ``name`` (imported on first use)."""
    if name not in REGISTRY:
        raise NimbusError(f"unknown rasterizer backend {name!r}; choose one of {', '.join(('auto', *REGISTRY))}")
    module, attr = REGISTRY[name].split(":")
    return getattr(importlib.import_module(module), attr)


def available(name: str, device="cpu") -> bool:
    """Whether backend ``name`` can render tensors on ``device`` on this machine."""
    import torch

    return bool(get(name).available(torch.device(device)))


def resolve(name: str, device) -> Backend:
    """The backend that renders for ``name`` (a registered name or ``"auto"``) on ``device``.

    ``"auto"`` picks the available backend with the highest ``auto_rank`` (gsplat on CUDA
    when it imports, else the compiled kernels on the CPU when they build, else torch).
    A backend asked for by name that cannot run here is an error, not a fallback.
    """
    if name == "auto":
        ranked = sorted((b for b in map(get, REGISTRY) if b.auto_rank is not None), key=lambda b: -b.auto_rank)
        for backend in ranked:
            if backend.available(device):
                return backend
        raise NimbusError(f"no rasterizer backend can render on {device}")  # torch always can
    backend = get(name)
    if not backend.available(device):
        raise NimbusError(f"backend {name!r} needs {backend.needs}; use backend='torch' or 'auto' on this machine")
    return backend
