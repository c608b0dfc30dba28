"""Thesis chapter 6: depth of your own stabilised video (infer, footage, network) with multiple
frame shifts (multishift), and the shift strategies scored on generated sequences
(multishift_eval)."""
