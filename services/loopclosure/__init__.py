"""RatSLAM local view: view templates of each frame, matched against every stored template, and
the paper's consistency rule that turns repeated matches into confirmed loop closures."""
