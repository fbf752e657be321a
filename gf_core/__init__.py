"""GaussFluids engine. One package per stage of the data flow (docs/architecture.md):

- ``formats``   sim.h5 / recon.h5, the numpy decoder, PLY / glTF / VTK, USD and OpenVDB caches
                (numpy and h5py only: the Blender extension bundles this package whole)
- ``native``    the one C++/CUDA extension: its sources, build and cache
- ``render``    differentiable splatting: ``render()`` with the pure-torch reference and the native backend
- ``sph``       smoothing kernels, neighbour search, SPH density
- ``sim``       the DFSPH and PBF simulators, their registry and scenes
- ``data``      dataset layouts (a registry of detect / load), images, lens models
- ``recon``     the reconstruction: config and presets, model, decoder, loss terms, schedule, trainer
- ``eval``      metrics, ``gf-cli evaluate``, in-between frames
- ``downstream`` prediction, editing and exports of a reconstruction
- ``bench``     ``gf-cli bench``

Modules are imported on use; ``camera``, ``errors``, ``formats`` and ``data`` need no torch.
"""

__version__ = "0.1.0"
