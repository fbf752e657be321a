"""The toolkit's files, numpy and h5py only (the Blender extension bundles this package whole):
``hdf5`` (sim.h5 and recon.h5: versioned, validated on read, written atomically), ``decoder_np``
(the reconstruction's decoder in numpy), ``ply`` / ``gltf`` / ``vtk`` (Gaussians and particles for
other tools), ``caches`` (USD points and OpenVDB density, through Blender's or the user's pxr /
openvdb), ``toml_file`` (presets, configs and suites)."""
