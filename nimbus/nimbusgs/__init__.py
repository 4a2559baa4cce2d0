"""NimbusGS: weather-robust Gaussian splatting (continuous scattering, particulate residuals, GGS).

Modules: :mod:`~nimbus.nimbusgs.config` (settings and presets), :mod:`~nimbus.nimbusgs.scattering`
(extinction field and ray march), :mod:`~nimbus.nimbusgs.airlight`, :mod:`~nimbus.nimbusgs.particulate`
(residual store), :mod:`~nimbus.nimbusgs.ggs` (gradient scaling), :mod:`~nimbus.nimbusgs.losses`,
:mod:`~nimbus.nimbusgs.auto` (component selection) and :mod:`~nimbus.nimbusgs.degradation` (the
degradation model: medium, composite, residuals); the classical 2D restoration of an ablation is shared with
the ``restore-3dgs`` baseline in :mod:`nimbus.restore.classical`.  The method itself, built on these, is :mod:`nimbus.methods.nimbusgs`; its named
variants are in :mod:`nimbus.methods.registry`.
"""
