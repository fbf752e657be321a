"""SPH building blocks shared by the simulators, the reconstruction's density loss and the
evaluation: smoothing kernels (``kernels``), fixed-radius and K-nearest neighbour search
(``neighbors``) and the number density over neighbour lists (``density``)."""
