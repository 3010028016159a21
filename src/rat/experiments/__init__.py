"""Experiments apart from the library: presets as data, the paper's numbers and table-1 grid, and
the glue from names (victim specs, targets, methods, presets) to runs. The library never imports
this package."""
