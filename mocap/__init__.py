"""Motion data: file formats (ASF/AMC, BVH, CSV), channels, representation, data sets,
fill protocols, metrics and the simple baselines."""
