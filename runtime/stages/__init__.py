"""The stages of an Engine's frame, each an object that is handed what it needs.

characters.py poses the neural characters and places their billboards (and their regions'),
decides what each needs, and runs their networks on a thread of their own; prims.py draws the
scene prims' G-buffer and lights and shadows it; composite.py lights and shadows the
characters' layers and composites them over the prims. Engine.render (runtime/engine.py)
decides what runs and when; FrameState (runtime/frame.py) carries a frame through them.
"""
