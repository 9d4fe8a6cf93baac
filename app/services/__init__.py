"""The service layer: what a request does, between the HTTP routers and the registry.

Imports the registry, the schemas and the science core, never FastAPI. The routers of
:mod:`app.api` parse, call one function or object here, and return its schema.
"""
