"""Simulated rig physics: paper Eq. 3 three-mass chain, sensor chain and the effect catalogue."""
