"""``/`` leads to the API documentation, and its pages load nothing from outside the server:
on a robot's network without the internet ``/docs`` (Swagger UI) and ``/redoc`` still work."""

from __future__ import annotations

import re

from conftest import InProcess


def test_the_root_redirects_to_the_docs(api: InProcess) -> None:
    with api.http(timeout=30, follow_redirects=False) as h:
        r = h.get("/")
        assert r.status_code in (302, 307) and r.headers["location"] == "/docs"
        assert h.get("/", follow_redirects=True).url.path == "/docs"


def test_the_docs_pages_load_only_from_the_server(api: InProcess) -> None:
    with api.http(timeout=30) as h:
        for page, needs in (("/docs", ("swagger-ui-bundle.js", "swagger-ui.css")),
                            ("/redoc", ("redoc.standalone.js",))):
            r = h.get(page)
            assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
            html = r.text
            assert not re.findall(r"(?:https?:)?//[\w.-]+\.\w+", html), page  # no external URL
            assets = re.findall(r"""(?:src|href)=["']([^"']+)["']""", html)
            assert all(any(a.endswith(n) for a in assets) for n in needs), (page, assets)
            for asset in assets:  # each one served here, whole
                got = h.get(asset)
                assert got.status_code == 200 and len(got.content) > 100, asset
            assert "/openapi.json" in html
        assert '"validatorUrl": null' in h.get("/docs").text  # no call to a public validator
