"""Stage 7, the surface: marching cubes and the closedness checks, streamed meshing slab by slab,
simplification within a tolerance, the mesh writers (one format registry) and printer slices."""
