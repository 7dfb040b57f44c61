#!/usr/bin/env bash
# Mitsuba 3's llvm_ad_rgb variant needs LLVM >= 16 at run time; Debian ships it as libllvm19.
# Install it when we are root with apt and it is missing; otherwise say what to do and go on
# (statmc then falls back to the scalar_rgb variant with a message).
set -u
for p in /usr/lib/x86_64-linux-gnu/libLLVM-19.so /usr/lib/aarch64-linux-gnu/libLLVM-19.so \
         /usr/lib/llvm-19/lib/libLLVM-19.so /usr/lib/llvm-19/lib/libLLVM.so.1; do
  if [ -e "$p" ]; then exit 0; fi
done
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "statmc: installing Debian's libllvm19 for Mitsuba's llvm_ad_rgb variant"
  export DEBIAN_FRONTEND=noninteractive
  (apt-get update -qq && apt-get install -y -qq libllvm19) >/tmp/statmc-apt.log 2>&1 \
    || echo "statmc: could not install libllvm19 (see /tmp/statmc-apt.log); Mitsuba will use scalar_rgb"
else
  echo "statmc: libLLVM-19 not found and not root; install 'libllvm19' for the fast Mitsuba variant"
fi
exit 0
