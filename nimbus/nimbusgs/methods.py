"""NimbusGS and its paper variants as named methods of ``nimbus-train --method``.

Importing this module registers them in :data:`nimbus.train.methods.METHODS`.  ``nimbus``
decides its components from the data (``components=auto``); the ablation variants
start from ``nimbus-full`` (every component forced on, as in the paper's ablations)
and change one thing.  Each is also reachable as ``--method nimbus --set ...``
(see :mod:`nimbus.nimbusgs.config`).
"""

from __future__ import annotations

import dataclasses
import functools

from nimbus.train.methods import Method, register

FULL = "csm,plm,ggs"

#: name -> (description, config changes applied on top of the preset); a callable value
#: is evaluated against the preset (for schedule-relative settings).
VARIANTS: dict[str, tuple[str, dict]] = {
    "nimbus": ("NimbusGS; components (CSM / PLM / GGS) chosen from the input views", {}),
    "nimbus-full": ("NimbusGS with every component forced on", {"components": FULL}),
    "nimbus-no-csm": ("NimbusGS without continuous scattering modelling", {"components": "plm,ggs"}),
    "nimbus-no-plm": ("NimbusGS without the particulate layer", {"components": "csm,ggs"}),
    "nimbus-no-ggs": ("NimbusGS without geometry-guided gradient scaling", {"components": "csm,plm"}),
    "nimbus-gaussian-extinction": ("ablation: extinction as a per-Gaussian attribute",
                                   {"components": FULL, "extinction": "gaussian"}),
    "nimbus-uniform-extinction": ("ablation: one global extinction coefficient",
                                  {"components": FULL, "extinction": "uniform"}),
    "nimbus-restored-residuals": ("ablation: residuals against a classical 2D restoration",
                                  {"components": FULL, "residual_source": "restored"}),
    "nimbus-ggs-no-depth": ("ablation: GGS without its depth factor", {"components": FULL, "ggs_depth": False}),
    "nimbus-ggs-no-radius": ("ablation: GGS without its radius factor", {"components": FULL, "ggs_radius": False}),
    "nimbus-ggs-no-error": ("ablation: GGS without its error factor", {"components": FULL, "ggs_error": False}),
    "nimbus-no-dcp": ("ablation: without the dark-channel loss", {"components": FULL, "lambda_dcp": 0.0}),
    "nimbus-dcp-stage2": ("ablation: dark-channel loss kept in stage 2", {"components": FULL, "dcp_stage2": True}),
    "nimbus-no-tv": ("ablation: without the TV loss on the extinction", {"components": FULL, "lambda_tv": 0.0}),
    "nimbus-airlight-constant": ("variant: one constant airlight colour", {"components": FULL, "airlight": "constant"}),
    "nimbus-airlight-sh": ("variant: airlight as SH of the ray direction (released code)",
                           {"components": FULL, "airlight": "sh"}),
}
#: The paper's M_init ablation (iterations of its 30k schedule), scaled to the preset.
M_INIT_VARIANTS = (1000, 2000, 4000, 10_000, 15_000)


def _trainer_class(name: str):
    from nimbus.nimbusgs.trainer import NimbusTrainer

    if name == "nimbus":
        return NimbusTrainer
    return _named_subclass(name)


@functools.lru_cache(maxsize=None)
def _named_subclass(name: str):
    from nimbus.nimbusgs.trainer import NimbusTrainer

    # The run records (and --resume looks up) the method by this name.
    return type(f"NimbusTrainer[{name}]", (NimbusTrainer,), {"method_name": name})


def _preset(changes: dict, m_init_paper: int | None, preset_name: str):
    from nimbus.nimbusgs.config import paper_m_init, preset

    config = preset(preset_name)
    if m_init_paper is not None:
        changes = {**changes, "m_init": paper_m_init(config, m_init_paper)}
    return dataclasses.replace(config, **changes)


def register_all() -> None:
    for name, (description, changes) in VARIANTS.items():
        register(Method(name, description, functools.partial(_trainer_class, name),
                        functools.partial(_preset, changes, None)))
    for k in M_INIT_VARIANTS:
        name = f"nimbus-minit-{k // 1000}k"
        register(Method(name, f"ablation: M_init = {k // 1000}k of the paper's 30k iterations, scaled to the preset",
                        functools.partial(_trainer_class, name),
                        functools.partial(_preset, {"components": FULL}, k)))


register_all()
