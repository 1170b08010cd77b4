"""Stages 1, 5 and 6 as signed distance fields on a voxel grid: the patient (primitives, meshes, CT
volumes), the lattice (paper and struts, on OpenCL), blending, the cut at a porosity's level, the
skin, repair offsets, and the field nodes that compose them slab by slab. Units are millimetres."""
