#!/usr/bin/env bash
# System packages that some tests use beyond pip: headless Chromium for the browser test of the
# textured glTF (tests/test_texture.py). Installed with Debian's apt when running as root (CI);
# otherwise the script says what to install and the browser test is skipped with that reason.
# It never fails the set-up: every other test runs without it.
if command -v chromium-headless-shell >/dev/null 2>&1 || command -v chromium >/dev/null 2>&1; then
    exit 0
fi
if [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing chromium-headless-shell (browser test of the textured glTF)" >&2
    export DEBIAN_FRONTEND=noninteractive
    { apt-get update -qq && apt-get install -y -qq --no-install-recommends chromium-headless-shell; } >/dev/null 2>&1 \
        || echo "could not install chromium-headless-shell: the browser test will be skipped" >&2
else
    echo "no headless Chromium (as root: apt-get install chromium-headless-shell): the browser test will be skipped" >&2
fi
exit 0
