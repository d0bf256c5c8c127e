#!/bin/bash
# The hand-made one-line bugs of docs/develop/mutation.md ("The one-line bugs put in by hand"), put back one
# at a time in a copy of the tree: each must make the tests of its own module fail (exit 1).
# run NAME TESTS FILE OLD NEW [FILE OLD NEW ...]: every replacement is made (the first occurrence).
# ONLY=REGEX runs only the bugs whose name matches (e.g. ONLY='^[1-6] '); PY=python to run (default .venv's).
set -u
SRC=$(cd "$(dirname "$0")/.." && pwd)
SLC_TESTS="tests/protocols/slc_ascii/test_transaction.py tests/test_sans_io.py tests/kinds/slc_ascii/test_driver.py tests/protocols/slc_ascii/test_transaction_safety.py tests/protocols/slc_ascii/test_transaction_state_machine.py tests/protocols/slc_ascii/test_transaction_read_own.py"
H_TESTS="tests/modbus/test_handler.py tests/modbus/test_server.py tests/test_hostile_network.py tests/modbus/test_server_slow_reader.py tests/test_register_image.py"
TARGET_TESTS="tests/kinds/df1/target/test_end_to_end.py tests/kinds/df1/target/test_persist_faults.py tests/kinds/df1/target/test_unit_floats.py"
ADMISSION_TESTS="tests/modbus/test_admission.py tests/modbus/test_server.py tests/test_hostile_network.py"
RESPONDER_TESTS="tests/protocols/df1/full_duplex/test_responder.py"
UNIT_TESTS="tests/test_register_image.py tests/kinds/test_not_polled.py tests/test_write_timeout.py tests/test_freshness_verdict.py"
FRESHNESS_TESTS="tests/test_freshness_verdict.py"
SLC_PLAN_TESTS="tests/kinds/slc_ascii/test_plan.py tests/protocols/slc_ascii/test_memory_map.py tests/kinds/slc_ascii/test_driver.py"
run() {
  name=$1; tests=$2; shift 2
  if [ -n "${ONLY:-}" ] && ! [[ "$name" =~ $ONLY ]]; then return; fi
  d=$(mktemp -d); cp -r $SRC/gateway $SRC/tests $SRC/pyproject.toml $d/
  while [ $# -ge 3 ]; do
    if ! python3 - "$d/$1" "$2" "$3" <<'PY'
import sys; p,old,new=sys.argv[1:]; s=open(p).read(); assert s.count(old)>=1,(p,old); open(p,'w').write(s.replace(old,new,1))
PY
    then echo "$name: NOT APPLIED: the line is no longer in $1 (update this script)"; rm -rf $d; return; fi
    shift 3
  done
  (cd $d && PYTHONPATH=$d timeout 900 ${PY:-$SRC/.venv/bin/python} -m pytest -q -x -p no:cacheprovider $tests > $d/out.txt 2>&1); rc=$?
  echo "$name: exit $rc $(tail -1 $d/out.txt)"; rm -rf $d
}
run "handler >= 0x10000" "$H_TESTS" gateway/modbus/handler.py "if address + count > 0x10000:" "if address + count >= 0x10000:"
run "handler tid & 0xFF" "$H_TESTS" gateway/modbus/handler.py "return _MBAP.pack(tid, 0, 1 + len(echo), unit) + echo" "return _MBAP.pack(tid & 0xFF, 0, 1 + len(echo), unit) + echo"
run "no resync before write in untrusted era" "$SLC_TESTS" gateway/protocols/slc_ascii/transaction.py "if self._next == 0 or (self._is_write and not (self._era_trusted and self._clean)):" "if self._next == 0:"
run "S4 messages==1 dropped" "$SLC_TESTS" gateway/protocols/slc_ascii/transaction.py "and self._messages == 1 and self._era_trusted:" "and self._era_trusted:"
run "_next = 0 after unknown/failed removed" "$SLC_TESTS" gateway/protocols/slc_ascii/transaction.py "            self._next = 0  # we no longer know" "            pass  # we no longer know"
run "S6 z_ever -> z_sent" "$SLC_TESTS" gateway/protocols/slc_ascii/transaction.py "z_sent=self._z_ever," "z_sent=bool(self._z_sent),"
# issue 33's bugs: each fails the tests of its own module, not only an end-to-end or soak test
run "1 target: STS 0 though the save failed" "$TARGET_TESTS" gateway/kinds/df1/target/driver.py "reply = self._commit(command, result)" "self._commit(command, result)"
run "2 target: a failed write not taken back" "$TARGET_TESTS" gateway/kinds/df1/target/unit.py "table_file.write_bytes(ref.element * size, bytes(self.cache.data[index]), stamp)" "pass"
run "3 admission: loopback or not allowed" "$ADMISSION_TESTS" gateway/modbus/admission.py "is_loopback and not host_allowed(" "is_loopback or not host_allowed("
run "4 responder: _last_reply kept on a new command" "$RESPONDER_TESTS" gateway/protocols/df1/full_duplex/responder.py "        self._last_reply = None
        self._pending.append(header)" "        self._pending.append(header)"
run "5 SLC: a late reply taken in resync" "$SLC_TESTS" gateway/protocols/slc_ascii/transaction.py "if (not self._is_write and self._copies and isinstance(event, DataReply)" "if (not self._is_write and isinstance(event, DataReply)"
run "5 SLC: the same, _msg_id given an initial value" "$SLC_TESTS" gateway/protocols/slc_ascii/transaction.py "if (not self._is_write and self._copies and isinstance(event, DataReply)" "if (not self._is_write and isinstance(event, DataReply)" gateway/protocols/slc_ascii/sender.py "        self._msg_id: int
" "        self._msg_id: int = 0
"
run "6 unit: silent-link limit min -> max" "$UNIT_TESTS" gateway/freshness.py "stale_after + min(schedule.period, default=0.0)" "stale_after + max(schedule.period, default=0.0)"
run "6 SLC plan: presets not masked" "$SLC_PLAN_TESTS" gateway/kinds/slc_ascii/plan.py "plan.holding[timers + n] = word(preset, U16_BE_MASKED," "plan.holding[timers + n] = word(preset, U16_BE,"
run "6 target: float word order" "$TARGET_TESTS" gateway/kinds/df1/target/unit.py 'low_first = entry.word_order == "low-first"' 'low_first = entry.word_order != "low-first"'
# issue 42's harms: each fails the tests of its own module
LINK_HEALTH_TESTS="tests/test_link_health.py"
run "42.1 link_health: failures counted across answers" "$LINK_HEALTH_TESTS" gateway/link_health.py "            self._failures_in_row = 0
            self._last_ok = now" "            self._last_ok = now"
run "42.2 link_health: never answered counts as available" "$LINK_HEALTH_TESTS" gateway/link_health.py "return self.connected and self._state is True" "return self.connected and self._state is not False"
TAGS_TESTS="tests/test_export_tags.py"
run "42.9 tags: int32 exported as DWord" "$TAGS_TESTS" gateway/tags.py '"int32": "Long"' '"int32": "DWord"'
run "42.10 tags: a 32-bit tag half outside writable read-write" "$TAGS_TESTS" gateway/tags.py "width = 2 if word_order else 1" "width = 1"
PAYLOAD_TESTS="tests/sparkplug/test_payload.py tests/sparkplug/test_node.py"
run "42.8 payload: the sign check ignores signed" "$PAYLOAD_TESTS" gateway/sparkplug/payload.py "return value - (1 << bits) if signed and value >> (bits - 1) else value" "return value - (1 << bits) if value >> (bits - 1) else value"
POLLER_TESTS="tests/test_poller_failures.py tests/test_poller_link_state.py tests/test_poller_availability.py tests/test_poller_freshness.py tests/test_poller_spread.py"
run "42.3 poller: a link down by timeouts not lost" "$POLLER_TESTS" gateway/poller.py "return self._responding is None or self._responding()" "return True"
run "42.4 poller: a refused block never cleared" "$POLLER_TESTS" gateway/poller.py "            del self.refused[index]
" "            pass
"
run "42.5 poller: no down_wait" "$POLLER_TESTS" gateway/poller.py "await asyncio.sleep(self._down_wait)" "await asyncio.sleep(0)"
CONNECTION_TESTS="tests/modbus/test_connection.py tests/modbus/test_server.py"
run "42.6 connection: a later request not held behind a waiting read" "$CONNECTION_TESTS" gateway/modbus/connection.py "                self._held = True" "                self._held = False"
run "42.13 SLC driver: a port write that fails leaves its transaction running" "$SLC_TESTS" gateway/kinds/slc_ascii/driver.py "                self.session.connected()  # not sent: the transaction ends here, and the next one resyncs" "                pass"
RELOAD_TESTS="tests/test_reload_keys.py tests/test_reload_plan.py"
run "42.11 reload: a changed TLS listen address counted as live" "$RELOAD_TESTS" gateway/reload.py '"modbus.tls": frozenset({"cert",' '"modbus.tls": frozenset({"listen", "cert",'
run "42.11 reload: a key in LIVE_KEYS without its handler" "$RELOAD_TESTS" gateway/reload.py '"metrics": frozenset({"allow", "max_connections"}),' '"metrics": frozenset({"allow", "max_connections", "listen"}),'
APP_RELOAD_TESTS="tests/e2e/test_sparkplug_reload.py tests/e2e/test_reload.py"
run "42.12 app: a reload that only removes links keeps the Sparkplug session" "$APP_RELOAD_TESTS" gateway/app.py "        if changes.started or changes.stopped:
            await self._renew_sparkplug()" "        if changes.started:
            await self._renew_sparkplug()"
SPARKPLUG_DRIVER_TESTS="tests/sparkplug/test_driver.py"
run "42.7 sparkplug driver: a lost session's outbox not drained" "$SPARKPLUG_DRIVER_TESTS" gateway/sparkplug/driver.py "                self._drain_outbox()
" "                pass
"
# issue 42's staleness harms: the stale limit moved from status.py into the one verdict (gateway/freshness.py)
run "42.s1 verdict: stale limit max -> min over the achieved periods" "$FRESHNESS_TESTS" gateway/freshness.py "return self.stale_after + max([achieved, *(schedule.period[i] for i in blocks)])" "return self.stale_after + min([achieved, *(schedule.period[i] for i in blocks)])"
run "42.s2 verdict: slow class included in the stale limit" "$FRESHNESS_TESTS" gateway/freshness.py 'if scan.value == "fast"] or list(' 'if scan.value in ("fast", "slow")] or list('
# issue 42's schedule harms
SCHEDULE_TESTS="tests/test_schedule.py"
run "42.s3 schedule: lateness judged against the initial limit" "$SCHEDULE_TESTS" gateway/schedule.py "late = now - last > self._stamped[block]" "late = now - last > self.stale_after + self.period[block]"
run "42.s4 schedule: a refused block's hold ends one period late" "$SCHEDULE_TESTS" gateway/schedule.py "        self.due[block] = self.held_until[block] = until
" "        self.held_until[block] = until
        self.due[block] = until + self.period[block]
"
