"""Every reconstruction method by name, with its class and presets imported only when used.

``nimbus-train --method NAME``, ``nimbus-bench run`` and ``nimbus-bench tables`` look methods up
here.  Adding a method is one file implementing :class:`~nimbus.methods.base.Method` and one
entry in :data:`METHODS` (nothing registers itself on import)::

    "my-method": MethodSpec("my-method", "what it is", "nimbus.methods.my_method:MyMethod"),

A method may have named variants (:class:`Variant`): ``nimbus`` has one entry, and its ablations
are variants of it, each reachable as ``--method nimbus-SUFFIX`` (and each also as ``--method nimbus
--set ...``, see :mod:`nimbus.methods.nimbusgs.config`).  ``nimbus`` decides its components from the
data (``components=auto``); the ablations start from every component forced on (``nimbus-full``,
as in the paper's ablations) and change one thing.  ``nimbus-paper`` (:data:`PAPER`) is NimbusGS
as the paper's text writes it: every component on and each of our departures from the paper set
back.  :data:`METHODS` lists every name, variants included; ``nimbus-train --method help`` prints
them grouped by entry.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from dataclasses import dataclass, field
from typing import Any, Callable

from nimbus.errors import NimbusError

#: ``module:function`` of the 3DGS presets (``preset(name) -> TrainConfig``) and of NimbusGS's.
GS_PRESETS = "nimbus.train.config:preset"
NIMBUS_PRESETS = "nimbus.methods.nimbusgs.config:preset"
NIMBUS = "nimbus.methods.nimbusgs.method:NimbusGS"
FULL = "csm,plm,ggs"


def _import(target: str) -> Any:
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class Variant:
    """A named variant of a registry entry: ``--method ENTRY-SUFFIX`` is the entry with ``changes``."""

    suffix: str
    description: str
    changes: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class MethodSpec:
    """A named reconstruction method.

    Attributes
    ----------
    name : str
    description : str
    target : str
        ``module:Class`` of the :class:`~nimbus.methods.base.Method` (imported by :meth:`load`).
    presets : str
        ``module:function`` mapping a preset name (``tiny``, ``fast``, ``paper``) to a config.
    changes : dict
        Config fields set on top of the preset; a callable value is called with the preset's config
        (for schedule-relative settings).
    """

    name: str
    description: str
    target: str
    presets: str = GS_PRESETS
    changes: dict[str, Any] = field(default_factory=dict)
    #: Named variants of this entry (``NAME-SUFFIX``), each its changes on top of the preset's config.
    variants: tuple[Variant, ...] = ()
    #: For a variant: the name of the entry it is a variant of.
    base: str | None = None

    def expand(self) -> list[MethodSpec]:
        """This entry and one spec per variant (``NAME-SUFFIX``), in order."""
        return [self, *(MethodSpec(f"{self.name}-{v.suffix}", v.description, self.target, self.presets,
                                   {**self.changes, **v.changes}, base=self.name) for v in self.variants)]

    def load(self) -> type:
        """The method's class."""
        return _import(self.target)

    def preset(self, preset_name: str):
        """The method's config for ``preset_name`` (raises NimbusError for an unknown preset)."""
        config = _import(self.presets)(preset_name)
        changes = {k: v(config) if callable(v) else v for k, v in self.changes.items()}
        return dataclasses.replace(config, **changes) if changes else config


def _paper_m_init(k: int) -> Callable:
    """``m_init`` of the paper's M_init = ``k`` (iterations of its 30k schedule), scaled to the preset."""
    def m_init(config) -> int:
        from nimbus.methods.nimbusgs.config import paper_m_init

        return paper_m_init(config, k)

    return m_init


#: ``nimbus-paper``: NimbusGS as the paper writes it (nimbusgs.tex: Method; supplementary Implementation
#: Details), each of our departures (documented as "ours" in :class:`~nimbus.methods.nimbusgs.config.NimbusConfig`)
#: set back to the paper's statement.  The preset's schedule and resolution (iterations, M_init's share,
#: Z_ref, grid size, K) are left as for ``nimbus``, so the two differ by these fields only; the ``paper``
#: preset gives the paper's 4k + 26k, 128^3, K = 64 (see README "Where we depart from the paper").
PAPER: dict[str, Any] = {
    "components": FULL,
    # PLM: R = ReLU(I_in - I_con), nothing else decides what enters R, every view re-rendered each Z_ref.
    "residual_outlier_sigmas": 0.0, "residual_tophat": 0.0, "consistency_neighbours": 0, "refresh_mode": "all",
    # CSM: L_DCP on every pixel; colours start at the SfM colours; the box is the 2x AABB of every centre.
    "dcp_surface_only": False, "init_dehaze": False, "box_scale": 2.0, "box_content_factor": 0.0,
    "view_density": False, "lambda_dehaze": 0.0,
    # GGS: the bare w_i / mean(w), no [0.5, 3] clip.
    "ggs_clip": (0.0, math.inf),
    # The airlight as the authors' released code trains it (GitHub lyy-ovo/NimbusGS): its loss calls
    # ``airlight_field.eval_sh``, one global RGB colour ``(tanh(b) + 1) / 2`` with ``b ~ N(0, 1e-3)`` (grey 0.5),
    # learned at its ``airlight_lr`` 5e-3; its default ``use_airlight_cnn=False``, and in CNN mode ``eval_sh``
    # still returns the CNN's global bias alone.  The paper's words (an MLP conditioned on I_in and T) leave the
    # input pixel in reach of the airlight, whose identity then solves stage 1 with T -> 0.
    "airlight": "constant", "airlight_init": 0.5, "lr_airlight": 5e-3,
    # The paper evaluates its airlight at every pixel (``fast`` evaluates the network per 2 x 2 block).
    "airlight_stride": 1,
}

#: The paper's M_init ablation (iterations of its 30k schedule), scaled to the preset.
M_INIT_VARIANTS = (1000, 2000, 4000, 10_000, 15_000)

def _ablation(suffix: str, description: str, **changes) -> Variant:
    """A NimbusGS ablation: every component forced on (as the paper's ablations), then ``changes``."""
    return Variant(suffix, description, {"components": FULL, **changes})


#: NimbusGS's variants (``nimbus-SUFFIX``).
NIMBUS_VARIANTS = (
    Variant("full", "NimbusGS with every component forced on", {"components": FULL}),
    Variant("paper", "NimbusGS as the paper writes it: every component, R = ReLU(I_in - I_con) unfiltered, "
            "DCP on every pixel, plain 2x box, unclipped GGS, the released code's global airlight", PAPER),
    Variant("no-csm", "NimbusGS without continuous scattering modelling", {"components": "plm,ggs"}),
    Variant("no-plm", "NimbusGS without the particulate layer", {"components": "csm,ggs"}),
    Variant("no-ggs", "NimbusGS without geometry-guided gradient scaling", {"components": "csm,plm"}),
    _ablation("gaussian-extinction", "ablation: extinction as a per-Gaussian attribute", extinction="gaussian"),
    _ablation("uniform-extinction", "ablation: one global extinction coefficient", extinction="uniform"),
    _ablation("restored-residuals", "ablation: residuals against a classical 2D restoration",
              residual_source="restored"),
    _ablation("ggs-no-depth", "ablation: GGS without its depth factor", ggs_depth=False),
    _ablation("ggs-no-radius", "ablation: GGS without its radius factor", ggs_radius=False),
    _ablation("ggs-no-error", "ablation: GGS without its error factor", ggs_error=False),
    _ablation("no-dcp", "ablation: without the dark-channel loss", lambda_dcp=0.0),
    _ablation("dcp-stage2", "ablation: dark-channel loss kept in stage 2", dcp_stage2=True),
    _ablation("no-tv", "ablation: without the TV loss on the extinction", lambda_tv=0.0),
    _ablation("airlight-constant", "variant: one constant airlight colour", airlight="constant"),
    _ablation("airlight-sh", "variant: airlight as SH of the ray direction (released code)", airlight="sh"),
    *(_ablation(f"minit-{k // 1000}k", f"ablation: M_init = {k // 1000}k of the paper's 30k iterations, scaled to "
                "the preset", m_init=_paper_m_init(k)) for k in M_INIT_VARIANTS),
)

#: The registry's entries (variants are listed with their entry).
ENTRIES = [
    MethodSpec("3dgs", "vanilla 3D Gaussian Splatting (Inria defaults)", "nimbus.methods.gs3d:GaussianSplatting"),
    MethodSpec("restore-3dgs", "two-stage baseline: each training view restored in 2D (dark-channel dehazing, "
               "particle removal or an ONNX model), then 3DGS", "nimbus.methods.restore_3dgs:RestoreThen3DGS",
               "nimbus.methods.restore_3dgs:preset"),
    MethodSpec("robust-3dgs", "3DGS whose loss drops outlier pixels (residual above a running quantile, voted, "
               "dilated): transients, rain, snow", "nimbus.methods.robust_3dgs:Robust3DGS",
               "nimbus.methods.robust_3dgs:preset"),
    MethodSpec("medium-3dgs", "3DGS in a learned homogeneous medium (per-channel attenuation and backscatter)",
               "nimbus.methods.medium_3dgs:Medium3DGS", "nimbus.methods.medium_3dgs:preset"),
    MethodSpec("nimbus", "NimbusGS; components (CSM / PLM / GGS) chosen from the input views", NIMBUS, NIMBUS_PRESETS,
               variants=NIMBUS_VARIANTS),
]

#: name -> :class:`MethodSpec` of every entry and variant, in the order above.
METHODS: dict[str, MethodSpec] = {spec.name: spec for entry in ENTRIES for spec in entry.expand()}


def method_help() -> str:
    """Every method, variants grouped under their entry: what ``nimbus-train --method help`` prints."""
    lines = []
    for entry in ENTRIES:
        lines.append(f"{entry.name:<28} {entry.description}")
        lines += [f"  {spec.name:<26} {spec.description}" for spec in entry.expand()[1:]]
    return "\n".join(lines)


def get_method(name: str) -> MethodSpec:
    try:
        return METHODS[name]
    except KeyError:
        raise NimbusError(f"unknown method {name!r}; choose one of: {', '.join(sorted(METHODS))}") from None
