from services.depth.service import cli

cli()
