// Room for the live point-cloud preview an edge capture agent will stream (not defined yet).
// main.js imports this module for /?live=URL and calls start({viewer, url, showMessage}).
// The viewer already draws point clouds: viewer.setPointCloud('live', positions, colours),
// positions a Float32Array of N*3 metres (world frame), colours N*3 in 0..1 or null; calling it
// again replaces the cloud, so a stream only has to decode frames and call it per frame.

export async function start({ url, showMessage }) {
  showMessage(`Live preview (${url}) is not available yet: the edge agent's stream comes with a later release.`, 'info');
}
