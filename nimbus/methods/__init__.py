"""Reconstruction methods: one protocol (:mod:`~nimbus.methods.base`), one module per method, one registry.

:mod:`~nimbus.methods.gs3d` is vanilla 3DGS, :mod:`nimbus.methods.nimbusgs` NimbusGS (a package: the method in
:mod:`~nimbus.methods.nimbusgs.method`, its degradation model, config and component selection beside it), and :mod:`~nimbus.methods.registry` names every method and its presets.
:class:`nimbus.train.runner.Runner` drives any of them.  Adding a method is one new file
implementing :class:`~nimbus.methods.base.Method` plus one line in the registry.
"""
