"""Stage 8 and after, measured on what was built: the paper's metrics, bone morphometry on the
voxels, mechanics (voxel finite elements, multigrid), and the print certificate."""
