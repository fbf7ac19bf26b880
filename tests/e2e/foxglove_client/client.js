// An outside Foxglove client for gridslam's tests (tests/e2e/test_ros.py): the npm
// @foxglove/ws-protocol FoxgloveClient over the ws package, offering only the subprotocol
// FoxgloveClient.SUPPORTED_SUBPROTOCOL ("foxglove.websocket.v1"). It subscribes to every
// advertised channel, keeps every message, and once nothing has arrived for QUIET_MS prints one
// JSON object: the subprotocol the server agreed to, the channels, every message (log time as a
// decimal string, payload in base64) and any error the client reported.
//
//   node client.js ws://127.0.0.1:8765 [QUIET_MS] [TIMEOUT_MS]
"use strict";

const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");

const [url, quietArg, timeoutArg] = process.argv.slice(2);
const QUIET_MS = Number(quietArg || 2000);
const TIMEOUT_MS = Number(timeoutArg || 60000);

const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const channels = new Map(); // channel id → channel
const subscriptions = new Map(); // subscription id → topic
const messages = {}; // topic → [[log time, base64 payload]]
const errors = [];
let serverInfo = null;
let lastArrival = Date.now();
let finished = false;

function finish(code) {
  if (finished) return;
  finished = true;
  const result = {
    offered: FoxgloveClient.SUPPORTED_SUBPROTOCOL,
    subprotocol: ws.protocol,
    serverInfo,
    channels: [...channels.values()].map(({ id, topic, encoding, schemaName, schemaEncoding }) => ({
      id, topic, encoding, schemaName, schemaEncoding,
    })),
    messages,
    errors,
  };
  process.stdout.write(JSON.stringify(result) + "\n", () => process.exit(code));
  client.close();
}

client.on("error", (error) => errors.push(String(error && error.message ? error.message : error)));
client.on("serverInfo", (info) => {
  serverInfo = info;
});
client.on("advertise", (advertised) => {
  for (const channel of advertised) {
    channels.set(channel.id, channel);
    subscriptions.set(client.subscribe(channel.id), channel.topic);
  }
  lastArrival = Date.now();
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const topic = subscriptions.get(subscriptionId);
  const payload = Buffer.from(data.buffer, data.byteOffset, data.byteLength).toString("base64");
  (messages[topic] = messages[topic] || []).push([timestamp.toString(), payload]);
  lastArrival = Date.now();
});
client.on("close", (event) => {
  if (!finished) {
    errors.push(`closed: ${event && event.code}`);
    finish(1);
  }
});

const started = Date.now();
setInterval(() => {
  if (channels.size > 0 && Date.now() - lastArrival > QUIET_MS) finish(0);
  else if (Date.now() - started > TIMEOUT_MS) {
    errors.push("timed out");
    finish(1);
  }
}, 100);
