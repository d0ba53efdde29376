"""World simulator: environments, targets, drones, camera, scripted pilot."""
