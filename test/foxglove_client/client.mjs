// A Foxglove WebSocket client as Lichtblick and older Foxglove Studio builds are made:
// @foxglove/ws-protocol's FoxgloveClient over a `ws` socket, schemas parsed with
// @foxglove/rosmsg and CDR decoded with @foxglove/rosmsg2-serialization.
//
//   node client.mjs URL SUBPROTOCOL SECONDS
//
// Offers only SUBPROTOCOL, subscribes to every advertised channel, decodes every message for
// SECONDS after the first advertise, then prints one JSON object on stdout: the negotiated
// subprotocol, the channels, messages decoded and decode errors per topic, DeviceState
// messages per half second, the protocol errors and the first decoded message's field names per
// topic. Exit status 0 when it ran (the caller judges the figures), 2 on bad arguments,
// 3 when the connection failed.
import wsProtocol from "@foxglove/ws-protocol";
import rosmsg from "@foxglove/rosmsg";
import rosmsg2 from "@foxglove/rosmsg2-serialization";
import WebSocket from "ws";

// CommonJS packages: their exports come as one default object.
const { FoxgloveClient } = wsProtocol;
const { parse } = rosmsg;
const { MessageReader } = rosmsg2;

const [url, subprotocol, secondsArg] = process.argv.slice(2);
const seconds = Number(secondsArg);
if (!url || !subprotocol || !(seconds > 0)) {
  console.error("usage: node client.mjs URL SUBPROTOCOL SECONDS (SECONDS > 0)");
  process.exit(2);
}

const STATE = "haptic_topology_msgs/msg/DeviceState";
const ws = new WebSocket(url, [subprotocol]);
const client = new FoxgloveClient({ ws });
const report = {
  subprotocol: null, serverName: null, channels: {}, decoded: {}, decodeErrors: {},
  firstFields: {}, stateBins: [], errors: [], closed: null,
};
const bySubscription = new Map();
let started = null;

client.on("open", () => { report.subprotocol = ws.protocol; });
client.on("serverInfo", (info) => { report.serverName = info.name; });
client.on("error", (err) => { report.errors.push(String(err?.message ?? err)); });
client.on("close", (ev) => { report.closed = ev?.code ?? true; });
client.on("advertise", (channels) => {
  if (started === null) {
    started = Date.now();
    setTimeout(finish, seconds * 1000);
  }
  for (const ch of channels) {
    report.channels[ch.topic] = {
      id: ch.id, encoding: ch.encoding, schemaName: ch.schemaName,
      schemaEncoding: ch.schemaEncoding,
    };
    report.decoded[ch.topic] = 0;
    report.decodeErrors[ch.topic] = 0;
    let reader = null;
    try {
      if (ch.encoding !== "cdr" || ch.schemaEncoding !== "ros2msg") {
        throw new Error(`encoding ${ch.encoding}/${ch.schemaEncoding}, expected cdr/ros2msg`);
      }
      reader = new MessageReader(parse(ch.schema, { ros2: true }));
    } catch (err) {
      report.errors.push(`${ch.topic}: schema: ${err.message}`);
    }
    bySubscription.set(client.subscribe(ch.id), { topic: ch.topic, reader, type: ch.schemaName });
  }
});
client.on("message", ({ subscriptionId, data }) => {
  const sub = bySubscription.get(subscriptionId);
  if (!sub) {
    report.errors.push(`message for unknown subscription ${subscriptionId}`);
    return;
  }
  try {
    if (!sub.reader) throw new Error("no schema");
    const msg = sub.reader.readMessage(new Uint8Array(data.buffer, data.byteOffset, data.byteLength));
    report.decoded[sub.topic] += 1;
    if (!(sub.topic in report.firstFields)) report.firstFields[sub.topic] = Object.keys(msg);
    if (sub.type === STATE) {
      const bin = Math.floor((Date.now() - started) / 500);
      while (report.stateBins.length <= bin) report.stateBins.push(0);
      report.stateBins[bin] += 1;
    }
  } catch (err) {
    report.decodeErrors[sub.topic] += 1;
    if (report.decodeErrors[sub.topic] === 1) report.errors.push(`${sub.topic}: ${err.message}`);
  }
});

function finish() {
  client.close();
  process.stdout.write(JSON.stringify(report) + "\n");
  process.exit(0);
}

ws.on("unexpected-response", (_req, res) => {
  console.error(`connection refused: HTTP ${res.statusCode}`);
  process.exit(3);
});
ws.on("error", (err) => {
  if (started === null) {
    console.error(`connection failed: ${err.message}`);
    process.exit(3);
  }
});
// Never hang: give up 60 s after the planned end.
setTimeout(() => { report.errors.push("no advertise in time"); finish(); },
  (seconds + 60) * 1000).unref();
