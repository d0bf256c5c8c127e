#!/bin/bash
# The hand-made one-line bugs of docs/develop/mutation.md ("The one-line bugs put in by hand"), put back one
# at a time in a copy of the tree: each must make the tests of its own module fail (exit 1).
set -u
SRC=$(cd "$(dirname "$0")/.." && pwd)
SLC_TESTS="tests/test_slc_transaction.py tests/test_sans_io.py tests/test_driver_slc_ascii.py tests/test_slc_transaction_safety.py tests/test_slc_transaction_state_machine.py"
H_TESTS="tests/test_modbus_handler.py tests/test_modbus_server.py tests/test_hostile_network.py tests/test_server_slow_reader.py tests/test_register_image.py"
run() { # name file python-replace-old python-replace-new tests
  d=$(mktemp -d); cp -r $SRC/gateway $SRC/tests $SRC/pyproject.toml $d/
  python3 - "$d/$2" "$3" "$4" <<'PY'
import sys; p,old,new=sys.argv[1:]; s=open(p).read(); assert s.count(old)>=1,(p,old); open(p,'w').write(s.replace(old,new,1))
PY
  (cd $d && PYTHONPATH=$d timeout 900 $SRC/.venv/bin/python -m pytest -q -x -p no:cacheprovider $5 > $d/out.txt 2>&1); rc=$?
  echo "$1: exit $rc $(tail -1 $d/out.txt)"; rm -rf $d
}
run "handler >= 0x10000" gateway/modbus/handler.py "if address + count > 0x10000:" "if address + count >= 0x10000:" "$H_TESTS"
run "handler tid & 0xFF" gateway/modbus/handler.py "return _MBAP.pack(tid, 0, 1 + len(echo), unit) + echo" "return _MBAP.pack(tid & 0xFF, 0, 1 + len(echo), unit) + echo" "$H_TESTS"
run "no resync before write in untrusted era" gateway/protocols/slc_ascii/transaction.py "if self._next == 0 or (self._is_write and not (self._era_trusted and self._clean)):" "if self._next == 0:" "$SLC_TESTS"
run "S4 messages==1 dropped" gateway/protocols/slc_ascii/transaction.py "and self._messages == 1 and self._era_trusted:" "and self._era_trusted:" "$SLC_TESTS"
run "_next = 0 after unknown/failed removed" gateway/protocols/slc_ascii/transaction.py "            self._next = 0  # we no longer know" "            pass  # we no longer know" "$SLC_TESTS"
run "S6 z_ever -> z_sent" gateway/protocols/slc_ascii/transaction.py "z_sent=self._z_ever," "z_sent=bool(self._z_sent)," "$SLC_TESTS"
