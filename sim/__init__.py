"""The simulated rig: firmware and camera emulators, the stone world, the DNG writer. Built on demand, never at import."""
