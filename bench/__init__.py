"""`rigspace bench`: run time against error, skip costs, memory, and numerical stability.

The one package allowed to import all the others (capture, train, runtime): it measures
them side by side in one run.
"""
