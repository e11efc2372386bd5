"""Launch limits the stages share."""

# register cap of the MPR, GJK and multi-contact kernels: uncapped they sit at 255 registers,
# which leaves 8 warps an SM to hide their memory latency; at 128 (16 warps) they spill a few
# hundred bytes to the stack and still run faster (docs/performance.md, "Register cap")
HEAVY_REGISTERS = 128
GRID_THREADS = 1 << 20  # cap of the grid-stride launches: each thread strides over the rest
