"""Stages 2-4, the geometry before any grid: seeds, their Voronoi cells, the scaled skeleton
(pores, channels, rims, rails), and the seed density of graded scaffolds. Units are millimetres."""
