"""Light profiles: elliptical Sérsic (lens light) and pixelated sources (COSMOS).

All return surface brightness in e⁻/s per arcsec²; multiply by the pixel area
(arcsec²) for e⁻/s per pixel.
"""

from subslope.physics.light.pixelated import PixelatedSource, pad_stamps, pixelated_light
from subslope.physics.light.sersic import (
    ZERO_POINT_F814W,
    SersicEllipse,
    flux_to_magnitude,
    magnitude_to_flux,
    sersic_amp_from_flux,
    sersic_b_n,
    sersic_ellipse,
    sersic_ellipse_from_magnitude,
    sersic_total_flux,
)

__all__ = [
    "PixelatedSource",
    "pad_stamps",
    "pixelated_light",
    "ZERO_POINT_F814W",
    "SersicEllipse",
    "flux_to_magnitude",
    "magnitude_to_flux",
    "sersic_amp_from_flux",
    "sersic_b_n",
    "sersic_ellipse",
    "sersic_ellipse_from_magnitude",
    "sersic_total_flux",
]
