"""Methods: the Gaussian core, 2D supervision sources, language fields and registered methods."""
