"""Thesis chapter 6: depth of your own stabilised video with multiple frame shifts (infer: the
frame loop and its outputs), and the shift strategies scored on generated sequences
(multishift_eval). The maths (core.multishift), the footage (core.footage) and the network on it
(engine.network, engine.footage_job, engine.frame_depth) are shared with other chapters."""
