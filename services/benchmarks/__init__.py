"""Benchmarks and the test scenes they render: `gridslam bench NAME` runs the module named here
for it (services/cli/bench.py). They stand above the services and import them; no service
imports them."""
