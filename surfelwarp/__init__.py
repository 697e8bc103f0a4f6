"""SurfelWarp (Gao & Tedrake 2018) and its DynamicFusion baseline, from single depth streams."""
import os

# The compiled kernels run on numba's threads. numpy's OpenBLAS keeps its own threads spinning
# for a while after every product, and on a machine with few cores they take the cores from
# numba's: on 640x480 colour scenes, 40 frames, one OpenBLAS thread made a frame 4-8 % faster
# (sheet 392 -> 376 ms, twist-limb 1428 -> 1314) and the colour stage 10-30 % (sheet 110 -> 77).
# Only before numpy is first imported does this take effect; a value the user set is kept.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# Likewise OpenMP (numba's threads, pykdtree's queries): its threads spin after a parallel
# region by default, and a spinning pool takes the core the next pool's query needs (touch, 40
# frames: the append stage, a k-d tree query after a compiled pass, 12.4 -> 5.1 ms).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
