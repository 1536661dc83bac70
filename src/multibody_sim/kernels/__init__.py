"""Kernels: the rows' states and the arithmetic of a step, which the stepping core (core.py) drives.

- base.py: the protocols: Kernel (the rows' states, what Core's records, stops and torques need: every kernel) and
  StepKernel (one step at a time, for the loop that runs in Python: Core.advance).
- row.py: RowKernel, the integrator's own attempt() row by row: the specification, and the kernel of every run the
  compiled extension does not take.
- native.py: NativeKernel and NativeCore, the compiled rendering (src/native/), and why_not_native, the rule for when
  it runs.

driver.choose_kernel picks one for a run. This package's __init__ imports nothing: core.py imports kernels.base, and
kernels.native imports the core.
"""
