"""Bundle-adjustment layer: what any least-squares problem over cameras and points needs.

Bottom to top: ``compiled`` (the numba switch), ``robust`` (robust kernels), ``state``
(:class:`~slam_bridge.ba.state.BAState` and its retraction), ``factor`` (the factor protocol and
its residual block), ``normal_equations`` (assembly of the block normal equations) and
``solvers`` (Schur complement, Levenberg-Marquardt, the barrier fusion). No concrete factor
lives here (they are in :mod:`slam_bridge.factors`, one layer up).
"""
