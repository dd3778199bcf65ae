"""Dense surface from the known poses: a depth map per keyframe by multi-view stereo (``depth``), fused into a
truncated signed distance volume (``fusion``), meshed with colour. The kernels are Warp (``dense.warp``), one
code for the CPU and CUDA; the types that pass between the parts are in ``dense.types``."""
