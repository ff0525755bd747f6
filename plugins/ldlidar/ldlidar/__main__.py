import os
import sys

# No command calls BLAS, yet OpenBLAS starts a thread per core as NumPy loads
# (tens of ms of CPU, taken from the decoder's own threads). This only takes
# effect because importing the package does not load NumPy.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from ._cli import main

sys.exit(main())
