#!/usr/bin/env bash
# Chromium for the report's browser test (tests/harness/test_report.py): installed
# with apt-get where that works here, otherwise skipped with the reason printed (the
# test then skips itself). Never fails the build.
set -u
if command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1; then
    exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "note: chromium not installed (no apt-get here); the report's browser test will be skipped"
    exit 0
fi
if [ "$(id -u)" -eq 0 ]; then
    run=()
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    run=(sudo -n)
else
    echo "note: chromium not installed (apt-get needs root; run: sudo apt-get install chromium);" \
         "the report's browser test will be skipped"
    exit 0
fi
install() {
    DEBIAN_FRONTEND=noninteractive "${run[@]}" apt-get install -y -q --no-install-recommends chromium \
        >>/tmp/hil-chromium-apt.log 2>&1
}
echo "installing chromium with apt-get (for the report's browser test)"
if ! install && ! { "${run[@]}" apt-get update -q >>/tmp/hil-chromium-apt.log 2>&1 && install; }; then
    echo "note: apt-get install chromium failed (see /tmp/hil-chromium-apt.log); the report's browser test will be skipped"
fi
exit 0
