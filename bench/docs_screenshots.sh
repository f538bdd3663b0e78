#!/usr/bin/env bash
# The documentation site's screenshots, docs/screenshots/home.png and own-predictor.png: build the
# site (mkdocs.yml), serve it on localhost and render two pages with headless Chromium.
#
#     bash bench/docs_screenshots.sh            # needs: pip install -e ".[docs]"; apt-get install -y chromium
#
# PORT (default 8765) picks the local port; CHROMIUM the browser binary.
set -euo pipefail
cd "$(dirname "$0")/.."
port="${PORT:-8765}"
browser="${CHROMIUM:-$(command -v chromium || command -v chromium-browser || command -v google-chrome)}"
site="$(mktemp -d)"
profile="$(mktemp -d)"
NO_MKDOCS_2_WARNING=1 python -m mkdocs build --strict --quiet --site-dir "$site"
python -m http.server "$port" --bind 127.0.0.1 --directory "$site" >/dev/null 2>&1 &
server=$!
trap 'kill "$server"; rm -rf "$site" "$profile"' EXIT
for _ in $(seq 50); do curl -sf "http://127.0.0.1:$port/" >/dev/null && break; sleep 0.1; done
shoot() {  # shoot URL_PATH OUT.png
    "$browser" --headless --no-sandbox --disable-gpu --hide-scrollbars --user-data-dir="$profile" \
        --window-size=1280,1600 --virtual-time-budget=3000 --screenshot="$2" "http://127.0.0.1:$port/$1" 2>/dev/null
}
mkdir -p docs/screenshots
shoot "" docs/screenshots/home.png
shoot "guides/own-predictor/" docs/screenshots/own-predictor.png
echo "wrote docs/screenshots/home.png, docs/screenshots/own-predictor.png"
