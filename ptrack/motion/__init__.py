"""Motion models: the PCA model of a motion class and its key postures. Imports `body` and the leaf
utilities."""
