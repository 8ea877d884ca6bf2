"""Tools around the pipeline, not stages of it: the ``logdesc-rt`` command line
(:mod:`.cli`) and pictures (:mod:`.plotting`, needs matplotlib). The pipeline's stages are the
package's other modules (sampling, normalization, geometry, network, matching, pose,
verification, refinement; io for files; batch and align for many pairs and scans)."""
