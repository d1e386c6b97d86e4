"""Offline 3D shape tracking of schooling fish (seed 004, Butail & Paley 2012).

May import: util, geometry.
"""
