"""Shared by every overgrid service and client: settings, keys, codec, lattice, camera and sensor math.

Importing this package never imports mujoco or cv2: a robot that only queries the map installs the base
package alone (DESIGN.md, Packaging).
"""
