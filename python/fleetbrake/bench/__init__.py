"""Benchmarks that print their figures beside a peer or a limit (``pip install
"fleetbrake[bench]"`` for the peers)."""
