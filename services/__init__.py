"""overgrid services: camera_sim, depth, fusion; each one process wired to Zenoh."""
