"""CDM: single-image point-cloud reconstruction with 2D and 3D priors (CVPR 2025), in pure PyTorch."""
