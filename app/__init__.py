"""The volumesh gateway (FastAPI) and the command line."""
