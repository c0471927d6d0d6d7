"""recon: inverse-rendering reconstruction with its own differentiable torch rasterizer."""

__version__ = "0.1.0"
