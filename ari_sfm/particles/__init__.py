"""Particles behind the window: correspondences, reconstruction of whole experiments, detection.

``match.py``: one frame's correspondences through the window (refracted epipolar curves, exact model);
``volume.py``: the measured volume; ``detect.py``: particle images -> sub-pixel centres;
``reconstruct.py``: whole experiments, frames in partitions on Dask (``engine.py``).
"""
