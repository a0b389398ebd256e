"""Simulated vehicles that are real protocol peers: Crazyflies speaking CRTP over UDP (``SimSwarm`` in
``swarm.py``) and MAVLink vehicles. Import the submodules directly; this package imports nothing."""
