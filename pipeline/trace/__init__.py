"""CPU path tracer for the inserted objects (wavefront NumPy on Embree).

Modules: :mod:`~pipeline.trace.intersect` (ray casting backends), :mod:`~pipeline.trace.sampling`,
:mod:`~pipeline.trace.bsdf`, :mod:`~pipeline.trace.lights`, :mod:`~pipeline.trace.scene`,
:mod:`~pipeline.trace.pbr` (integrator and AO), :mod:`~pipeline.trace.shadow`,
:mod:`~pipeline.trace.denoise`, and :mod:`~pipeline.trace.stage` (the pipeline stage,
``pipeline.trace.stage:STAGE``). Importing this package imports nothing heavy.
"""
