from services.camera_sim.service import cli

cli()
