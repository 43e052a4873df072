"""The packaged scenario files (sim.yaml, hil.yaml, real.yaml); see systems/scenario.py."""
