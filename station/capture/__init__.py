"""Camera drivers (PTP over pyusb) and the scan session that runs a plan against the rig."""
