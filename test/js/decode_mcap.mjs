// Decode every message of an MCAP file with the libraries Foxglove's viewer decodes ROS 2 logs
// with (@mcap/core, @foxglove/rosmsg, @foxglove/rosmsg2-serialization), from the schemas the
// file carries; print per topic the message count and the decoded messages as JSON lines.
// Usage: node decode_mcap.mjs LOG.mcap
import { readFileSync } from 'node:fs';
import { McapStreamReader } from '@mcap/core';
import { parse } from '@foxglove/rosmsg';
import { MessageReader } from '@foxglove/rosmsg2-serialization';
import zstd from '@foxglove/wasm-zstd';

await zstd.isLoaded;
const reader = new McapStreamReader({
  decompressHandlers: { zstd: (data, size) => zstd.decompress(data, Number(size)) },
});
reader.append(new Uint8Array(readFileSync(process.argv[2])));
const schemas = new Map();
const channels = new Map();
const decoders = new Map();
const out = {};
for (let record; (record = reader.nextRecord()) !== undefined;) {
  if (record.type === 'Schema') {
    schemas.set(record.id, record);
  } else if (record.type === 'Channel') {
    channels.set(record.id, record);
    const schema = schemas.get(record.schemaId);
    if (schema.encoding !== 'ros2msg' || record.messageEncoding !== 'cdr') {
      throw new Error(`${record.topic}: ${schema.encoding} / ${record.messageEncoding}`);
    }
    const text = new TextDecoder().decode(schema.data);
    decoders.set(record.id, new MessageReader(parse(text, { ros2: true })));
    // the summary section repeats schemas and channels
    out[record.topic] ??= { type: schema.name, messages: [] };
  } else if (record.type === 'Message') {
    const channel = channels.get(record.channelId);
    const message = decoders.get(record.channelId).readMessage(record.data);
    out[channel.topic].messages.push({ log_time: record.logTime.toString(), message });
  }
}
process.stdout.write(JSON.stringify(out, (k, v) => (typeof v === 'bigint' ? v.toString()
  : v instanceof Uint8Array ? Array.from(v) : v)));
