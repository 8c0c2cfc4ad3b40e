"""acinoset's job service: a REST API (FastAPI) that runs :func:`graph.api.solve` for a whole lab.

:func:`service.app.create_app` builds the application; ``acinoset serve`` runs it.
"""
