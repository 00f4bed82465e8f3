// Describe one LAS/LAZ/COPC file as the npm `copc` package (copc.js, the
// reader of the COPC web viewers) reads it, as JSON on stdout.
//
//   node bench/interop/read_copc.mjs FILE [--las]
//
// A COPC file goes through Copc.create (header, VLRs and EVLRs, WKT, extra-bytes
// descriptors, COPC info), then every hierarchy page and every node's points
// (Copc.loadPointDataView). With --las (or a file without the COPC info VLR)
// the same Las.* helpers read a plain LAS/LAZ file: header, VLRs, WKT,
// extra-bytes descriptors, and every point (Las.PointData.decompressFile for LAZ).
//
// Points are printed per node as integer grid coordinates
// (round((X - offset) / scale)) and colors, so that bench/interop.py compares
// them exactly with laspy's; extra-bytes dimensions as their min and max over
// the points read. A reader's exception is printed as {"error": ...} with exit 2.
import { readFileSync } from 'node:fs';
import copcPkg from 'copc';

const { Copc, Las } = copcPkg;

function jsonable(v) {
  return JSON.stringify(v, (k, x) => (typeof x === 'bigint' ? x.toString() : x));
}

function pointsOf(view, header, ebs) {
  const n = view.pointCount;
  const get = (name) => (view.dimensions[name] ? view.getter(name) : null);
  const [sx, sy, sz] = header.scale;
  const [ox, oy, oz] = header.offset;
  const gx = get('X'), gy = get('Y'), gz = get('Z');
  const gr = get('Red'), gg = get('Green'), gb = get('Blue');
  const out = { X: [], Y: [], Z: [], R: [], G: [], B: [] };
  for (let i = 0; i < n; ++i) {
    out.X.push(Math.round((gx(i) - ox) / sx));
    out.Y.push(Math.round((gy(i) - oy) / sy));
    out.Z.push(Math.round((gz(i) - oz) / sz));
    if (gr) {
      out.R.push(gr(i));
      out.G.push(gg(i));
      out.B.push(gb(i));
    }
  }
  const extra = {};
  for (const eb of ebs) {
    const g = get(eb.name);
    if (!g) {
      extra[eb.name] = { error: 'no dimension in the view' };
      continue;
    }
    let lo = Infinity, hi = -Infinity;
    for (let i = 0; i < n; ++i) {
      const v = Number(g(i));
      if (v < lo) lo = v;
      if (v > hi) hi = v;
    }
    extra[eb.name] = n ? { min: lo, max: hi } : {};
  }
  return { count: n, points: out, extra };
}

function describeVlrs(vlrs) {
  return vlrs.map((v) => ({
    userId: v.userId,
    recordId: v.recordId,
    contentLength: v.contentLength,
    description: v.description,
    isExtended: v.isExtended,
  }));
}

async function readCopc(file) {
  const copc = await Copc.create(file);
  const { header, vlrs, info, wkt, eb } = copc;
  // every page, breadth first
  const nodes = {};
  const pages = [info.rootHierarchyPage];
  let pagesRead = 0;
  while (pages.length) {
    const page = pages.shift();
    const h = await Copc.loadHierarchyPage(file, page);
    pagesRead += 1;
    Object.assign(nodes, h.nodes);
    pages.push(...Object.values(h.pages));
  }
  const perNode = {};
  for (const [key, node] of Object.entries(nodes)) {
    const entry = { pointCount: node.pointCount };
    if (node.pointCount > 0) {
      const view = await Copc.loadPointDataView(file, copc, node);
      Object.assign(entry, pointsOf(view, header, eb));
    } else {
      entry.count = 0;
    }
    perNode[key] = entry;
  }
  return { kind: 'copc', header, vlrs: describeVlrs(vlrs), info, wkt: wkt ?? null, eb, hierarchyPages: pagesRead, nodes: perNode };
}

async function readLas(file) {
  const buf = readFileSync(file);
  const bytes = new Uint8Array(buf.buffer, buf.byteOffset, buf.byteLength);
  const get = async (begin, end) => bytes.slice(begin, end);
  const header = Las.Header.parse(bytes.slice(0, 375));
  const vlrs = await Las.Vlr.walk(get, header);
  let wkt = null;
  const wktVlr = Las.Vlr.find(vlrs, 'LASF_Projection', 2112);
  if (wktVlr && wktVlr.contentLength) {
    const raw = await Las.Vlr.fetch(get, wktVlr);
    wkt = new TextDecoder().decode(raw).replace(/\0.*$/s, '') || null;
  }
  let eb = [];
  const ebVlr = Las.Vlr.find(vlrs, 'LASF_Spec', 4);
  if (ebVlr) eb = Las.ExtraBytes.parse(await Las.Vlr.fetch(get, ebVlr));
  const compressed = (bytes[104] & 0x80) !== 0;
  let data;
  if (compressed) {
    data = await Las.PointData.decompressFile(bytes);
  } else {
    const start = header.pointDataOffset;
    data = bytes.slice(start, start + header.pointCount * header.pointDataRecordLength);
  }
  const view = Las.View.create(data, header, eb);
  return {
    kind: compressed ? 'laz' : 'las',
    header,
    vlrs: describeVlrs(vlrs),
    wkt,
    eb,
    nodes: { all: { pointCount: header.pointCount, ...pointsOf(view, header, eb) } },
  };
}

async function main() {
  const args = process.argv.slice(2);
  const file = args.find((a) => !a.startsWith('--'));
  if (!file) {
    process.stderr.write('usage: node read_copc.mjs FILE [--las]\n');
    process.exit(64);
  }
  let version = null;
  try {
    version = JSON.parse(readFileSync(new URL('./node_modules/copc/package.json', import.meta.url))).version;
  } catch {}
  try {
    let result;
    if (args.includes('--las')) {
      result = await readLas(file);
    } else {
      result = await readCopc(file);
    }
    process.stdout.write(jsonable({ reader: `copc@${version}`, file, ...result }) + '\n');
  } catch (e) {
    process.stdout.write(jsonable({ reader: `copc@${version}`, file, error: String(e && e.message ? e.message : e) }) + '\n');
    process.exit(2);
  }
}

main();
