"""Trajectory evaluation: file formats (TUM, KITTI; the motion inputs of every kind in
motion_io.py), metrics (ATE, RPE, KITTI drift, per-frame errors), results folders and plots.

The maths is written here from the papers it cites (evo is GPL and is not copied); every
stage of the pipeline and every command writes and scores its trajectories through this
package, so that numbers in different reports mean the same thing.
"""
