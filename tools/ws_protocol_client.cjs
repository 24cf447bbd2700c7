// A Foxglove WebSocket viewer as other tools are built: the @foxglove/ws-protocol
// client (subprotocol foxglove.websocket.v1) on the `ws` package (node 20 has no
// global WebSocket). Used by tests/harness/test_live.py; needs both packages on
// NODE_PATH (the test installs them with npm into a temporary folder).
//
//   node tools/ws_protocol_client.cjs URL TOPIC COUNT
//
// Prints one JSON line per event on stdout: {"open": subprotocol}, {"serverInfo": name},
// {"channel": {...}} for TOPIC's advertisement, then {"message": {...}} for each of the
// first COUNT messages on TOPIC (its payload parsed as JSON); exits 0 after them,
// 1 on an error or a close before them.
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");

const [url, topic, countText] = process.argv.slice(2);
const count = Number(countText);
const say = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");
const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
let subscription = null;
let got = 0;
client.on("open", () => say({ open: ws.protocol }));
client.on("serverInfo", (info) => say({ serverInfo: info.name }));
client.on("advertise", (channels) => {
  for (const ch of channels) {
    if (ch.topic === topic && subscription === null) {
      say({ channel: { topic: ch.topic, encoding: ch.encoding, schemaName: ch.schemaName } });
      subscription = client.subscribe(ch.id);
    }
  }
});
client.on("message", (m) => {
  if (m.subscriptionId !== subscription) return;
  const text = new TextDecoder().decode(m.data);
  say({ message: { timestamp: m.timestamp.toString(), data: JSON.parse(text) } });
  if (++got >= count) {
    client.close();
    process.exit(0);
  }
});
client.on("error", (err) => {
  say({ error: String(err && err.message ? err.message : err) });
  process.exit(1);
});
client.on("close", (ev) => {
  say({ close: ev && ev.code });
  process.exit(1);
});
