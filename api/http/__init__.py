"""The HTTP door: routes, schemas, the request guard, errors, the live view and the page.

Handlers are thin (parse, authorise, call the cell, shape JSON); everything under
``/api/v1`` passes the request guard first.
"""
