"""What every layer uses and none computes: the one memo and the disk cache (``cache``), Ctrl-C
(``interrupt``), BLAS threads and kernels (``threads``), progress bars (``progress``)."""
