"""RatSLAM experience map: experiences and links built from odometry, view templates and
confirmed loop closures, relaxed into a consistent map, persisted as it grows."""
