"""DroneFL."""
