"""Scenes: declared physics (locks, springs, friction, forces, payloads, constraints) on a robot."""
