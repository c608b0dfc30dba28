"""Closed-loop obstacle avoidance in generated scenes (thesis 6.5, in simulation): the pure core.

Frames and units, everywhere in this package: metres, seconds, radians. The world frame is
stillbox_gen's (right-handed, +Z up, the scene's first camera position at the origin). Camera
poses are OpenCV camera-to-world 4x4 matrices (x right, y down, z forward), as in
:mod:`stillbox_gen.camera`. Nothing here imports Blender.
"""
