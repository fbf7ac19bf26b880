"""Shared runtime: config, flags, codec, session, service base, logging; and what the stages
share: frames (frames.py), geometry (SE(2) and SE(3), geometry.py), features and their tracking
(features.py), image conversions (images.py), path integration of increments (odometry.py)."""
