"""NimbusGS: weather-robust Gaussian splatting (continuous scattering, particulate residuals, GGS).

Modules: :mod:`~nimbus.nimbusgs.config` (settings and presets), :mod:`~nimbus.nimbusgs.scattering`
(extinction field and ray march), :mod:`~nimbus.nimbusgs.airlight`, :mod:`~nimbus.nimbusgs.particulate`
(residual store), :mod:`~nimbus.nimbusgs.ggs` (gradient scaling), :mod:`~nimbus.nimbusgs.losses`,
:mod:`~nimbus.nimbusgs.auto` (component selection), :mod:`~nimbus.nimbusgs.restore` (classical 2D
restoration for an ablation) and :mod:`~nimbus.nimbusgs.degradation` (the degradation model: medium,
composite, residuals).  The method itself, built on these, is :mod:`nimbus.methods.nimbusgs`; its named
variants are in :mod:`nimbus.methods.registry`.
"""
