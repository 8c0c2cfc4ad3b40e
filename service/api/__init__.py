"""The HTTP layer: the REST routes, the web pages, who calls (auth), the request limits and headers,
and the JSON models the API answers with. Thin: the work is :mod:`service.core`'s."""
