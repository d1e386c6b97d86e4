"""The edge side in Python: the C feature extractor's binding (`features`) and the OAK camera edge
(`oak`). Edge management and video at the edges land here.

May import: util, protocol, geometry.
"""
