"""Runtime: stage + model bundle (+ live sources) -> per-frame evaluation -> composite -> images.

Never imports torch or rigspace.train: deployment needs only the base install.
"""
