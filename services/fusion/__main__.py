from services.fusion.service import cli

cli()
