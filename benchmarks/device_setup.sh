#!/usr/bin/env bash
# Prepare a bare lent machine (a Python with numpy, SciPy, OpenCV and numba, no network) to run
# this checkout's benchmarks: install the wheels carried in .whl/ into that Python, put the
# checkout's packages on its path, and write the `hmcc` command beside it (the tests' and the
# benchmarks' service processes start `hmcc` from the interpreter's folder).
#
# Here, once (the wheels this project needs that the lent image lacks, for Python 3.12):
#     echo /.whl/ >> .git/info/exclude; echo /.dev/ >> .git/info/exclude
#     python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 \
#         --platform manylinux2014_x86_64 -d .whl pydantic pydantic_core fastapi ...
#     mkdir -p .dev/lib; cp /usr/bin/redis-server .dev/lib/redis-server.bin; cp the libraries
#     `ldd` names that the image lacks (liblzf, libjemalloc) to .dev/lib; .dev/redis-server is
#     a wrapper: LD_LIBRARY_PATH=<its folder>/lib exec <its folder>/lib/redis-server.bin "$@"
# There, carrying .whl and .dev:
#     benchmarks/device_setup.sh && export PATH=$PWD/.dev:$PATH && OUT=$OUT/r PYTHON=python3 \
#         benchmarks/scale_device.sh
set -euo pipefail
PY=${PYTHON:-python3}
exe=$("$PY" -c 'import sys; print(sys.executable)')
site=$("$PY" -c 'import site; print(site.getsitepackages()[0])')
"$PY" -m pip install -q --no-index --no-deps .whl/*.whl
printf '%s\n' "$PWD/worker" "$PWD/service" "$PWD/client" > "$site/hmcc-checkout.pth"
# the checkout's bytecode, as an installed package has it (else, where PYTHONDONTWRITEBYTECODE
# is set, every process the benchmarks start compiles the project's modules again)
"$PY" -m compileall -q -j 0 worker service client benchmarks >/dev/null
for dist in hmcc_match hmcc_client; do  # importlib.metadata.version() of the packages
    mkdir -p "$site/$dist-0.1.0.dist-info"
    printf 'Metadata-Version: 2.1\nName: %s\nVersion: 0.1.0\n' "${dist/_/-}" \
        > "$site/$dist-0.1.0.dist-info/METADATA"
done
# the guard matters: compute children are spawned, and spawn runs the main script again
printf '#!%s\nimport sys\nfrom hmcc_cli import main\nif __name__ == "__main__":\n    sys.exit(main())\n' \
    "$exe" > "$(dirname "$exe")/hmcc"
chmod +x "$(dirname "$exe")/hmcc"
"$PY" -c 'import hmcc_cli, hmcc_client, numba, cv2; print("ready:", numba.__version__, cv2.__version__)'
