"""pranet.core: the numpy-only contract of the PRANet MDP, shared by training and service.

Frame convention, used everywhere in this package: ``T_target_source`` (4x4) maps source points
onto target points, ``target ≈ R @ source + t``; with points as rows, ``target ≈ source @ R.T + t``.
"""

__version__ = "0.1.0"
