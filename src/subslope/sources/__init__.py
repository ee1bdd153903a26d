"""Source-light catalogues: real COSMOS galaxies (default) and parametric alternatives."""
