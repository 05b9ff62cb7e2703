// The live preview of a stream (/?live=STREAM_ID): the gateway's WebSocket
// /api/v1/streams/{id}/preview relays the point cloud an edge agent sends with each frame-set
// (docs/api.md, "Live preview"); each one replaces the 'live' point-cloud layer. Also the list
// of the key's receiving streams, with links here.
import { API, ApiError, apiFetch, apiKey } from './api.js';
import { boundsOf } from './render.js';

const FORMAT = 'volumesh.preview/1';
const CLOSE_BAD_KEY = 4401;
const CLOSE_NO_STREAM = 4404;
const RECONNECT_MS = 2000;
const RATE_WINDOW_MS = 2000;

// sRGB bytes to the linear values three.js expects of vertex colours.
const SRGB_TO_LINEAR = Float32Array.from({ length: 256 }, (_, i) => {
  const c = i / 255;
  return c <= 0.04045 ? c / 12.92 : ((c + 0.055) / 1.055) ** 2.4;
});

/**
 * Decodes a preview.bin: {frameIndex, capturedAt, count, positions (Float32Array N*3, metres,
 * world), colors (Float32Array N*3, linear 0..1)}. Throws on a malformed buffer.
 */
export function decodePreview(buffer) {
  const fail = (why) => { throw new Error(`malformed live preview: ${why}`); };
  if (buffer.byteLength < 4) fail('too short');
  const headerLength = new DataView(buffer).getUint32(0, true);
  if (headerLength > 4096 || 4 + headerLength > buffer.byteLength) fail(`header length ${headerLength}`);
  let header;
  try {
    header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, headerLength)));
  } catch {
    fail('the header is not JSON');
  }
  const count = header?.points;
  if (header?.format !== FORMAT || !Number.isInteger(count) || count < 0) fail('not a volumesh.preview/1 header');
  const at = 4 + headerLength;
  if (buffer.byteLength !== at + 15 * count) fail(`${buffer.byteLength} bytes for ${count} points`);
  // A Float32Array over the buffer needs a 4-byte aligned offset (the agent pads its header
  // for that); otherwise copy. Browsers are little-endian, as the format is.
  const positions = at % 4 === 0
    ? new Float32Array(buffer, at, count * 3)
    : new Float32Array(buffer.slice(at, at + 12 * count));
  const rgb = new Uint8Array(buffer, at + 12 * count, count * 3);
  const colors = new Float32Array(count * 3);
  for (let i = 0; i < colors.length; i += 1) colors[i] = SRGB_TO_LINEAR[rgb[i]];
  return { frameIndex: header.frame_index, capturedAt: header.captured_at, count, positions, colors };
}

export function previewSocketUrl(streamId) {
  const scheme = location.protocol === 'https:' ? 'wss' : 'ws';
  return `${scheme}://${location.host}${API}/streams/${encodeURIComponent(streamId)}/preview`;
}

/**
 * Shows stream `streamId` live in `viewer` until it stops; `status` is the element of the
 * status line (inside `bar`). Resolves once the socket is open; the state is published on
 * window.viewerStats.live.
 */
/** A button that queues the capture's every frame as one job (a sequence) and says so. */
function reconstructButton(captureId, status, onJob) {
  const button = document.createElement('button');
  button.type = 'button';
  button.id = 'live-reconstruct';
  button.textContent = 'Reconstruct';
  button.title = 'Queue a job on every frame of the assembled capture';
  button.addEventListener('click', async () => {
    button.disabled = true;
    try {
      const job = await apiFetch('jobs', { method: 'POST', json: { capture_id: captureId, frames: 'all' } });
      status.append(` job ${String(job.id).slice(0, 12)} queued: it plays here when done (Jobs).`);
      onJob?.(job);
    } catch (err) {
      button.disabled = false;
      status.append(` ${err.message}`);
    }
  });
  return button;
}

export async function start({ viewer, streamId, showMessage, bar, status, onJob }) {
  const stats = { state: 'connecting', frameIndex: null, points: 0, updates: 0, rate: 0, ageMs: null, closed: null };
  window.viewerStats.live = stats;
  bar.hidden = false;
  const arrivals = [];
  let fitted = false;
  let lastFrame = -1;

  const showStatus = () => {
    if (stats.closed) return;
    if (stats.frameIndex === null) {
      status.textContent = `Stream ${streamId.slice(0, 12)}: ${stats.state === 'live' ? 'waiting for the first preview…' : `${stats.state}…`}`;
      return;
    }
    const age = stats.ageMs === null ? '–' : `${Math.round(stats.ageMs)} ms`;
    status.textContent = `frame ${stats.frameIndex} · ${stats.points.toLocaleString('en')} points · `
      + `${stats.rate.toFixed(1)} updates/s · age ${age}`;
  };

  const onPreview = (buffer) => {
    const preview = decodePreview(buffer);
    if (preview.frameIndex <= lastFrame) return; // after a reconnect the newest comes again
    lastFrame = preview.frameIndex;
    viewer.setPointCloud('live', preview.positions, preview.colors);
    if (!fitted && preview.count > 0) {
      viewer.fitToView(boundsOf(viewer.layers.get('live')));
      fitted = true;
    }
    const now = performance.now();
    arrivals.push(now);
    while (arrivals.length > 2 && now - arrivals[0] > RATE_WINDOW_MS) arrivals.shift();
    const spanMs = now - arrivals[0];
    // Age needs the agent's and this machine's clocks to agree (NTP: a few ms).
    Object.assign(stats, {
      frameIndex: preview.frameIndex, points: preview.count, updates: stats.updates + 1,
      rate: spanMs > 0 ? ((arrivals.length - 1) * 1000) / spanMs : 0,
      ageMs: Date.now() - preview.capturedAt * 1000,
    });
    showStatus();
  };

  const onState = (message) => {
    stats.state = message.state;
    if (message.state === 'assembling') {
      status.textContent = `Stream ${streamId.slice(0, 12)} stopped at frame ${stats.frameIndex ?? '–'}: assembling its capture…`;
      return;
    }
    stats.closed = message.state;
    status.replaceChildren(`Stream ${streamId.slice(0, 12)} ${message.state}`);
    if (message.capture_id) {
      status.append(`: capture ${message.capture_id.slice(0, 12)} `, reconstructButton(message.capture_id, status, onJob));
    } else if (message.error) {
      status.append(`: ${message.error}`);
    }
  };

  const connect = () => new Promise((resolve) => {
    const socket = new WebSocket(previewSocketUrl(streamId));
    socket.binaryType = 'arraybuffer';
    socket.onopen = () => {
      socket.send(JSON.stringify({ key: apiKey() }));
      stats.state = 'live';
      showStatus();
      resolve();
    };
    socket.onmessage = (event) => {
      try {
        if (typeof event.data === 'string') onState(JSON.parse(event.data));
        else onPreview(event.data);
      } catch (err) {
        showMessage(err.message);
      }
    };
    socket.onclose = (event) => {
      resolve();
      if (event.code === CLOSE_BAD_KEY) {
        stats.closed = 'unauthorized';
        showMessage('The live preview needs your API key: enter it under "API key" and reload.');
      } else if (event.code === CLOSE_NO_STREAM) {
        stats.closed = 'not found';
        showMessage(`There is no stream ${streamId} (or it is another owner's).`);
      } else if (!stats.closed) {
        stats.state = 'reconnecting';
        showStatus();
        setTimeout(connect, RECONNECT_MS); // the gateway restarted or the network dropped
      }
    };
  });
  showStatus();
  await connect();
}

/** Fills `list` with links to the key's receiving streams; hides `section` when there are none. */
export async function listLiveStreams(list, section) {
  if (!apiKey()) {
    section.hidden = true;
    return;
  }
  try {
    const { items } = await apiFetch('streams?state=receiving&limit=10');
    list.replaceChildren(...items.map(streamItem));
    section.hidden = items.length === 0;
  } catch (err) {
    list.textContent = err instanceof ApiError ? err.message : String(err);
    section.hidden = false;
  }
}

function streamItem(stream) {
  const item = document.createElement('li');
  const link = document.createElement('a');
  link.href = `/?live=${encodeURIComponent(stream.id)}`;
  link.textContent = stream.name || String(stream.id).slice(0, 12);
  item.append(link, ` ${stream.frames_received} frames`);
  return item;
}
