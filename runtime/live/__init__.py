"""Live input: sources (transport + sans-IO decoder), buffering and status, retargeting.

Data flow per binding: a transport thread reads bytes, a decoder turns them into timestamped
joint samples (`SourceFrame`), a `LiveBuffer` keeps, orders, smooths and times them, and the frame
thread asks the buffer for a `pose(now)` and retargets it onto the character (docs/live.md).
"""
