"""Device drivers, emulators and perception (installed as dexdrake.hardware)."""
