"""Multi-target 3D tracking: EKF per target, nearest-neighbour association, births and deaths.

May import: util, protocol, geometry.
"""
