# Sourced by scripts/bench-encoders.sh and scripts/bench-infer.sh (needs PY and OUT): the
# full-size random-weight CLIP ViT-B/32 (safetensors + ONNX export, written once into the asset
# cache by torch) in MODEL, and the 20 s 720p clip with a keyframe every second in CLIP.
bash scripts/fetch-assets.sh >/dev/null
ASSETS="${VLMFUSE_ASSETS:-$HOME/.cache/vlmfuse-assets}"
MODEL="$ASSETS/bench/clip-vit-b32-random"
"$PY" scripts/onnx/make_bench_model.py "$MODEL"
CLIP="$OUT/clip-20s-720p-gop30.mp4"
if [ ! -f "$CLIP" ]; then
  ffmpeg -hide_banner -loglevel error -nostdin -y -f lavfi \
    -i "testsrc2=size=1280x720:rate=30:duration=20,hue=H=2*PI*t/3" \
    -c:v libx264 -preset ultrafast -pix_fmt yuv420p -g 30 "$CLIP"
fi
