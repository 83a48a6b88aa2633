import torch
from mapf_policy.model_io import load_model
torch.set_num_threads(1)
d = torch.load('runs/probe/rowsS_1001.pt'); X, L, M = d['X'], d['L'], d['M']
seen = X[0][:, 1].flatten(1).sum(1) > 0
sel = ~M & seen
print('on-goal rows with a neighbour in view', int(sel.sum()), 'label stay share', float((L[sel] == 0).float().mean()))
net, _, _ = load_model('models/hscl.pt')
with torch.inference_mode():
    Xs = [x[sel] for x in X]
    q = torch.cat([net(*(x[i:i+4096] for x in Xs)) for i in range(0, int(sel.sum()), 4096)])
a = q.argmax(1); Ls = L[sel]
print('r108 argmax stay share', float((a == 0).float().mean()), 'agreement', float((a == Ls).float().mean()))
mv = Ls != 0
print('rows where the label moves', int(mv.sum()), 'r108 agrees there', float((a[mv] == Ls[mv]).float().mean()))
st = Ls == 0
print('rows where the label stays', int(st.sum()), 'r108 moves there', float((a[st] != 0).float().mean()))
