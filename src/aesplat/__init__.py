"""aesplat: pose-free feed-forward 3D Gaussian Splatting with decoupled appearance (AESplat)."""

__version__ = "0.1.0"
