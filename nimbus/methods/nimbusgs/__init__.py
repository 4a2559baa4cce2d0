"""NimbusGS: weather-robust Gaussian splatting (continuous scattering, particulate residuals, GGS).

Modules: :mod:`~nimbus.methods.nimbusgs.config` (settings and presets), :mod:`~nimbus.methods.nimbusgs.scattering`
(extinction field and ray march), :mod:`~nimbus.methods.nimbusgs.airlight`, :mod:`~nimbus.methods.nimbusgs.particulate`
(residual store), :mod:`~nimbus.methods.nimbusgs.ggs` (gradient scaling), :mod:`~nimbus.methods.nimbusgs.losses`,
:mod:`~nimbus.methods.nimbusgs.auto` (component selection) and :mod:`~nimbus.methods.nimbusgs.degradation` (the
degradation model: medium, composite, residuals); the classical 2D restoration of an ablation is shared with
the ``restore-3dgs`` baseline in :mod:`nimbus.restore.classical`.  The method itself, built on these, is
:mod:`~nimbus.methods.nimbusgs.method`; its named variants are in :mod:`nimbus.methods.registry`.
"""
