"""The whole stack as users run it: `gridslam run` and `gridslam demo` start every service as its
own process around a Zenoh router, record what they publish, and evaluate the run."""
