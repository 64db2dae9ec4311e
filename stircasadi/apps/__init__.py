"""Applications on the measured STIR and on the estimate: relighting, direct/global separation,
reflectance-based segmentation, material replacement and deconvolution of coded illumination
(issue 14). One application, one module; this face only re-exports."""
