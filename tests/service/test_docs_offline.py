"""``/docs`` (Swagger UI) and ``/redoc`` over real HTTP: every script, style and icon they name is served by the
service itself, so the pages work on a machine without internet (the browser test renders ``/docs`` with the
network blocked: ``tests/web/test_viewer.py``)."""

from __future__ import annotations

import re

import httpx
import pytest

ASSET_ATTRIBUTES = re.compile(r"""(?:src|href|spec-url)\s*=\s*["']([^"']+)["']""")


def _asset_urls(html: str) -> list[str]:
    return ASSET_ATTRIBUTES.findall(html)


def test_the_asset_parser_sees_a_cdn_link() -> None:
    """The oracle can fail: FastAPI's own page (CDN assets) is flagged."""
    from fastapi.openapi.docs import get_swagger_ui_html

    html = get_swagger_ui_html(openapi_url="/openapi.json", title="x").body.decode()
    assert any(url.startswith("https://") for url in _asset_urls(html))


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_reference_only_local_assets(http: httpx.Client, page: str) -> None:
    r = http.get(page)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    urls = _asset_urls(r.text)
    assert urls, f"{page} names no scripts or styles"
    remote = [u for u in urls if not u.startswith("/") or u.startswith("//")]
    assert not remote, f"{page} loads from the network: {remote}"
    assert "http://" not in r.text and "https://" not in r.text, f"{page} names an absolute URL"
    scripts = [u for u in urls if u.endswith(".js")]
    assert scripts, f"{page} names no script"
    for url in urls:
        asset = http.get(url)
        assert asset.status_code == 200 and len(asset.content) > 100, (url, asset.status_code)
    for url in scripts:
        assert "javascript" in http.get(url).headers["content-type"], url
