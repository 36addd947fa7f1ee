"""The localizer's stages, one module each (DESIGN.md, "Where each piece lives"): the place prior
(map-rendered profiles matched at every yaw) and the hypotheses (clusters, evidence, convergence). They
import numpy, scipy and rangemcl's numeric core only; the filter (``rangemcl.mcl``) composes them."""
