// Decode every message of an MCAP recording the way Foxglove's app does: @mcap/core's indexed
// reader, protobufjs types from the schema's embedded FileDescriptorSet. Prints one JSON line:
// counts per topic and schema, decode errors, and a few decoded samples for the test to check.
// usage: node decode_mcap.js FILE.mcap   (NODE_PATH: a folder with @mcap/core, protobufjs, fzstd)
"use strict";
const fs = require("fs");
const { McapIndexedReader } = require("@mcap/core");
const protobuf = require("protobufjs");
const { FileDescriptorSet } = require("protobufjs/ext/descriptor");
const fzstd = require("fzstd");

class FileReadable {
  constructor(fd, size) { this.fd = fd; this.sz = size; }
  async size() { return BigInt(this.sz); }
  async read(offset, length) {
    const buf = Buffer.alloc(Number(length));
    fs.readSync(this.fd, buf, 0, Number(length), Number(offset));
    return new Uint8Array(buf.buffer, buf.byteOffset, buf.byteLength);
  }
}

async function main() {
  const path = process.argv[2];
  const fd = fs.openSync(path, "r");
  const reader = await McapIndexedReader.Initialize({
    readable: new FileReadable(fd, fs.fstatSync(fd).size),
    decompressHandlers: { zstd: (data, size) => fzstd.decompress(data, new Uint8Array(Number(size))) },
  });
  const types = new Map();
  for (const [id, schema] of reader.schemasById) {
    const root = protobuf.Root.fromDescriptor(FileDescriptorSet.decode(schema.data));
    root.resolveAll();
    types.set(id, root.lookupType(schema.name));
  }
  const out = { topics: {}, schemas: {}, errors: 0, first_error: null, samples: {} };
  for (const [, ch] of reader.channelsById) {
    out.schemas[ch.topic] = reader.schemasById.get(ch.schemaId).name;
  }
  for await (const m of reader.readMessages()) {
    const ch = reader.channelsById.get(m.channelId);
    out.topics[ch.topic] = (out.topics[ch.topic] || 0) + 1;
    try {
      const obj = types.get(ch.schemaId).toObject(types.get(ch.schemaId).decode(m.data),
                                                  { longs: Number, enums: String, defaults: false });
      if (!(ch.topic in out.samples) || ch.topic === "/phase") out.samples[ch.topic] = obj;
    } catch (e) {
      out.errors += 1;
      if (!out.first_error) out.first_error = `${ch.topic}: ${e}`;
    }
  }
  process.stdout.write(JSON.stringify(out) + "\n");
}

main().catch((e) => { process.stderr.write(String(e && e.stack || e) + "\n"); process.exit(1); });
