"""gridslam services: pure algorithm cores and thin Zenoh adapters."""
