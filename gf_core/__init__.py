"""GaussFluids engine: Gaussian particles, differentiable splatting, simulators, file formats.

Modules are imported on use (``from gf_core import camera``); ``camera``, ``io`` and the dataset
loaders need only numpy/h5py/OpenCV, the renderer and everything that optimises needs torch.
"""

__version__ = "0.1.0"
