"""subslope: subhalo effective density slope from strong lensing with neural ratio estimation."""

__version__ = "0.1.0"
