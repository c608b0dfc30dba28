"""``stillbox-gen stats DIR``: data-quality figures of a generated dataset beside StillBox's.

Over the first N scenes it measures:

1. the pixel-depth distribution (planar depth as stored, metres; every frame of every scene):
   shares in fixed bands, median, share below 25 m and between 5 and 25 m;
2. wall and object pixels: a pixel is *wall* when its depth equals, within
   ``WALL_RTOL`` relative + ``WALL_ATOL`` metres, the planar depth at which its ray leaves the
   scene's axis-aligned box of walls (the camera is inside it); every other pixel is *object*;
3. the true optical flow at the nominal shift S: frame i's pixels moved into frame j = i + S by
   back-projecting depth_i, applying ``inv(cam2world_j) @ cam2world_i`` and projecting with K
   (pixels; median and 10/90 percentiles of its magnitude on walls and on objects);
4. the photometric residual (grey levels on 0-255, mean absolute difference over the three
   channels): ``|I_j - I_i|`` without warp, and after warping I_j back to frame i with the true
   flow (bilinear), on pixels that stay in frame j and are not occluded there;
5. optionally (``--flicker K``), the same-pose flicker: the pose of frame 0 of the first K scenes
   re-rendered by Blender with the dataset's own render settings as another frame of its scene,
   against the stored frame; and as frame 0 with another scene seed (sample placement only).

Averaging rule: pixels are pooled over all frames (depth, walls/objects) or all pairs
(i, i + S), i = 0 .. frames - 1 - S (flow, residuals) of the chosen scenes, every pixel weighing
the same. Medians and percentiles come from fine histograms (depth: 1 cm bins up to 250 m;
flow: log-spaced bins 0.46 % wide from 1e-3 to 1e3 px), linearly interpolated inside the bin.

Modules: :mod:`.histograms` (bands, fine histograms), :mod:`.geometry` (box depth, wall mask,
true flow, warp residuals), :mod:`.measure` (items 1-4 over a dataset), :mod:`.flicker` (item 5),
:mod:`.report` (text table, stats.png) and :mod:`.run` (the command: checks, measure, write).
None imports ``bpy``; ``--flicker`` renders through the generator's worker entry points in a
spawned process.
"""
