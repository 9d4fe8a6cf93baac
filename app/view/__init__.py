"""The live view's page, script and style (package data served by :mod:`app.api.view`)."""
