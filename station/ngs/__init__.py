"""Gaussian rasteriser, 3DGS/NGS trainer, infill and the Surface Opacity Score."""
