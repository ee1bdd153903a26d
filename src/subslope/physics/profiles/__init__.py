"""Lens mass profiles as pure, batched torch functions.

One profile per module; import the module you need, e.g.
``from subslope.physics.profiles.epl import epl_deflection``. This package file imports
nothing so that the profile modules stay independent of one another.

Modules: ``ellipse`` (e1, e2 <-> q, phi; rotations), ``epl`` (elliptical power law,
Tessore & Metcalf 2015), ``multipole`` (circular multipoles), ``shear`` (external
shear), ``sheet`` (uniform convergence sheet), ``nfw`` and ``tnfw``.
"""
